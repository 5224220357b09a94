"""Export a session to HDF5 (h5py, MATLAB, pandas via h5py) or to the analysis CSV format.

HDF5 layout::

    /                  attrs: format, uid, protocol, status, software, time, sample_time_s
    /channels/<name>   one 1-D dataset per channel, attr ``units``; ``force`` is the
                       exogenous force (the ``excitation`` channel, kept under both names)
    /records/start, /records/descriptor, /records/stop, /records/events
                       the non-sample records as JSON text (scalar string datasets:
                       unlike attributes they have no 64 kB limit)

CSV: ``# key=value`` metadata lines (docs/analysis.md: fs, ve, K, B, w0, td, protocol, ...),
a header row, then columns t, force, position and the other channels, floats
written with 17 significant digits so values round-trip exactly.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from labbench import records
from labbench.jsonutil import json_safe
from labbench.errors import UserError
from labbench.escape import one_line
from labbench.safe_write import output_path, replacing
from labbench.session_content import analysis_meta, load_session

FORMAT = "labbench-session-export 1"
# analysis columns first; the rest follow in records.CHANNELS order
CSV_COLUMNS = ("t", "force", "position") + tuple(
    c for c in records.CHANNELS if c not in ("t", "position", "excitation"))


def _json(obj) -> str:
    return json.dumps(json_safe(obj))


def export_hdf5(session_path, out_path, force: bool = False) -> Path:
    """Write the whole session to one HDF5 file; returns its path.

    An existing ``out_path`` is replaced only with ``force`` (``labbench.safe_write``).
    """
    import h5py

    output_path(out_path, [session_path], force)  # before the work
    start, desc, ch, events, stop, problem = load_session(session_path)
    units = dict(desc.get("channels") or records.CHANNELS)
    with replacing(out_path, [session_path], force) as tmp:
        try:
            f = h5py.File(tmp, "w")
        except OSError as exc:
            raise UserError(f"cannot write {out_path}: {exc}") from None
        with f:
            _fill_hdf5(f, session_path, start, desc, ch, events, stop, problem, units)
    return Path(out_path)


def _fill_hdf5(f, session_path, start, desc, ch, events, stop, problem, units) -> None:
    """The layout in the module doc."""
    f.attrs["format"] = FORMAT
    f.attrs["source"] = str(session_path)
    for key in ("uid", "software", "time"):
        if start.get(key) is not None:
            f.attrs[key] = start[key]
    f.attrs["protocol"] = analysis_meta(start, desc)["protocol"]
    f.attrs["status"] = str(stop.get("status")) if stop else "incomplete"
    if desc.get("sample_time_s"):
        f.attrs["sample_time_s"] = float(desc["sample_time_s"])
    if problem:
        f.attrs["damaged_tail"] = problem
    g = f.create_group("channels")
    for name, values in ch.items():
        g.create_dataset(name, data=values)
        g[name].attrs["units"] = units.get(name, "")
    g["force"] = g["excitation"]  # hard link: the analysis name of the exogenous force
    r = f.create_group("records")
    r["start"] = _json(start)
    r["descriptor"] = _json(desc)
    r["stop"] = _json(stop)
    r["events"] = _json(events)


def export_csv(session_path, out_path, force: bool = False) -> Path:
    """Write the analysis CSV (``# key=value`` lines, header, columns); returns its path.

    An existing ``out_path`` is replaced only with ``force`` (``labbench.safe_write``).
    """
    out = output_path(out_path, [session_path], force)  # before the work
    start, desc, ch, _events, _stop, _problem = load_session(session_path)
    meta = analysis_meta(start, desc)
    table = {"force": ch["excitation"], **ch}
    cols = np.column_stack([np.asarray(table[c], dtype=float) for c in CSV_COLUMNS])
    fmt = ["%d" if np.asarray(table[c]).dtype.kind in "iub" else "%.17g" for c in CSV_COLUMNS]
    header = "".join(f"# {k}={one_line(v)}\n" for k, v in meta.items()) + ",".join(CSV_COLUMNS)
    with replacing(out, [session_path], force) as tmp:
        try:
            np.savetxt(tmp, cols, delimiter=",", fmt=fmt, header=header, comments="")
        except OSError as exc:
            raise UserError(f"cannot write {out}: {exc.strerror}") from None
    return out
