"""Build the test drive: CANopenNode from ``../shared/third_party/CANopenNode`` (never
copied) with our transport, node and generated dictionary, into a shared library.

One ``cc`` call per variant; the output goes to a cache folder
(``$LABBENCH_CANOPENNODE_CACHE`` or ``~/.cache/labbench/canopennode``), one subfolder per
hash of everything that goes into it (sources, generated dictionary, flags, compiler), so
the suite builds once and rebuilds only when something changes. A subfolder is built
aside and renamed into place: concurrent suites never see half a build.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from canopennode import dictionary

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]  # the project's root
STACK = ROOT.parent / "shared" / "third_party" / "CANopenNode"  # ../shared/third_party/...
STACK_SOURCES = ("CANopen.c", "301/CO_ODinterface.c", "301/CO_NMT_Heartbeat.c",
                 "301/CO_HBconsumer.c", "301/CO_Node_Guarding.c", "301/CO_Emergency.c",
                 "301/CO_SDOserver.c", "301/CO_SYNC.c", "301/CO_PDO.c", "301/CO_fifo.c",
                 "301/crc16-ccitt.c")
OUR_SOURCES = ("CO_driver.c", "drive.c")
OUR_HEADERS = ("CO_driver_target.h",)
CFLAGS = ("-std=gnu11", "-O2", "-fPIC", "-shared")
LIB = "libcodrive.so"


class StackMissing(RuntimeError):
    """CANopenNode's sources are not where the project expects them."""


@dataclass(frozen=True)
class Built:
    lib: Path  # the shared library drive_process.py loads
    eds: Path  # the EDS the drive serves
    seconds: float  # compile time of this call (0 when cached)


def cache_root() -> Path:
    env = os.environ.get("LABBENCH_CANOPENNODE_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "labbench" / "canopennode"


def compiler() -> str:
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise StackMissing("no C compiler (cc or gcc) on PATH: the CANopenNode drive is built "
                           "with it")
    return cc


def _inputs(variant: str) -> dict[str, bytes]:
    """Every file of the build by its name in the build folder, generated ones included."""
    missing = [s for s in STACK_SOURCES if not (STACK / s).is_file()]
    if missing:
        what = ", ".join(missing) if STACK.is_dir() else "the folder"
        raise StackMissing(f"CANopenNode sources not found at {STACK} (missing {what}): the "
                           "tests build it from ../shared/third_party/CANopenNode beside the "
                           "project's root")
    files = {f"ours/{n}": (HERE / n).read_bytes() for n in OUR_SOURCES + OUR_HEADERS}
    files["ours/OD.h"] = dictionary.od_h(variant).encode()
    files["ours/OD.c"] = dictionary.od_c(variant).encode()
    for path in sorted(STACK.rglob("*.[ch]")):  # headers too: a change anywhere rebuilds
        files[f"stack/{path.relative_to(STACK)}"] = path.read_bytes()
    return files


def build(variant: str) -> Built:
    """The library and EDS of ``variant`` (``dictionary.VARIANTS``), built if not cached."""
    cc = compiler()
    version = subprocess.run([cc, "--version"], capture_output=True, text=True,
                             timeout=30).stdout.splitlines()[:1]
    files = _inputs(variant)
    h = hashlib.sha256(repr((variant, CFLAGS, version)).encode())
    for name in sorted(files):
        h.update(name.encode() + b"\0" + files[name] + b"\0")
    out = cache_root() / f"{variant}-{h.hexdigest()[:16]}"
    if (out / LIB).is_file():
        return Built(out / LIB, out / "drive.eds", 0.0)
    out.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
        work = Path(tmp) / "build"
        (work / "ours").mkdir(parents=True)
        for name in ("ours/OD.h", "ours/OD.c"):
            (work / name).write_bytes(files[name])
        (work / "drive.eds").write_text(dictionary.eds(variant))
        sources = [str(STACK / s) for s in STACK_SOURCES] + [str(HERE / s) for s in OUR_SOURCES]
        cmd = [cc, *CFLAGS, f"-I{STACK}", f"-I{HERE}", f"-I{work / 'ours'}", "-o",
               str(work / LIB), *sources, str(work / "ours" / "OD.c")]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        if proc.returncode:
            raise RuntimeError(f"building the CANopenNode drive failed ({' '.join(cmd)}):\n"
                               f"{proc.stderr[-4000:]}")
        try:
            work.rename(out)
        except OSError:  # another suite put the same build there first
            if not (out / LIB).is_file():
                raise
    return Built(out / LIB, out / "drive.eds", time.perf_counter() - t0)
