"""Exports from the window (HDF5, CSV, report), each run by the command line in a child process.

Drawing a report with matplotlib on a worker thread of the GUI process segfaulted
now and then (a cyclic GC pass there finalises Qt objects, and matplotlib is not
thread-safe): ``labbench export`` / ``labbench report`` in a child process has no
Qt in it, and whatever goes wrong there comes back as its one-line error. Nothing
is replaced: each export goes to a name not taken yet. No Qt here.
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from labbench.errors import UserError
from labbench.safe_write import free_name

EXPORT_TIMEOUT_S = 600.0


def export_in_child(path: str, fmt: str, out_dir: Path) -> list[Path]:
    """Export session ``path`` as ``fmt`` ("hdf5", "csv", "report") into ``out_dir``."""
    stem = Path(path).stem
    if fmt in ("hdf5", "csv"):
        target = free_name(Path(out_dir) / f"{stem}.{'h5' if fmt == 'hdf5' else 'csv'}")
        args = ["export", str(path), f"--{fmt}", str(target)]
    elif fmt == "report":
        target = free_name(Path(out_dir) / stem)
        args = ["report", str(path), "-o", str(target), "--json"]
    else:
        raise UserError(f"unknown export format {fmt!r}")
    try:
        done = subprocess.run([sys.executable, "-m", "labbench", *args], capture_output=True,
                              text=True, stdin=subprocess.DEVNULL, timeout=EXPORT_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        raise UserError(f"the {fmt} export of {path} took over {EXPORT_TIMEOUT_S:g} s") from None
    if done.returncode != 0:
        lines = done.stderr.strip().splitlines()
        raise UserError(lines[-1] if lines else f"the {fmt} export exited {done.returncode}")
    if fmt == "report":
        paths = json.loads(done.stdout)
        return [Path(paths["html"]), Path(paths["pdf"])]
    return [target]
