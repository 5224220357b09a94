"""Export a session to HDF5 (h5py, MATLAB, pandas via h5py) or to the analysis CSV format.

HDF5 layout::

    /                  attrs: format, uid, protocol, status, software, sample_time_s,
                       start_time (ISO 8601 with the UTC offset)
    /channels/t        the time axis [s], an HDF5 dimension scale ("time")
    /channels/<name>   one 1-D dataset per channel, attrs ``units`` and ``description``,
                       its dimension 0 attached to ``t`` (h5py ``dims``, netCDF-4 and
                       MATLAB see the axis); gzip level 4 with byte shuffle;
                       ``force`` is the exogenous force (the ``excitation`` channel,
                       kept under both names)
    /records/start, /records/descriptor, /records/stop, /records/events
                       the non-sample records as JSON text (scalar string datasets:
                       unlike attributes they have no 64 kB limit)

Frequency responses (``export_frequency_response``): CSV with ``# key=value`` lines
(estimator, source, bandwidths, theory plant), then one row per frequency: w in
rad/s and in Hz, Z, its 95 % radius, coherence, ES, ED, EM, and the theory's Z when
there is one. SI throughout (the frequency also in Hz, as plotted).

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
from labbench.readout.escape import one_line
from labbench.safe_write import output_path, replacing
from labbench.sessions.session_content import analysis_meta, load_session

FORMAT = "labbench-session-export 2"
COMPRESSION = {"compression": "gzip", "compression_opts": 4, "shuffle": True}
# analysis columns first; the rest follow in records.CHANNELS order
CSV_COLUMNS = ("t", "force", "position") + tuple(
    c for c in records.CHANNELS if c not in ("t", "position", "excitation"))


def _json(obj) -> str:
    return json.dumps(json_safe(obj))


def export_hdf5(session_path, out_path, force: bool = False, warn=None) -> Path:
    """Write the whole session to one HDF5 file; returns its path.

    An existing ``out_path`` is replaced only with ``force`` (``labbench.safe_write``).
    """
    import h5py

    output_path(out_path, [session_path], force)  # before the work
    start, desc, ch, events, stop, problem = load_session(session_path, warn, need_start=True)
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
    for key in ("uid", "software"):
        if start.get(key) is not None:
            f.attrs[key] = start[key]
    if start.get("time") is not None:
        f.attrs["start_time"] = records.iso_time(start["time"])
    f.attrs["protocol"] = analysis_meta(start, desc)["protocol"]
    f.attrs["status"] = str(stop.get("status")) if stop else "incomplete"
    if desc.get("sample_time_s"):
        f.attrs["sample_time_s"] = float(desc["sample_time_s"])
    if problem:
        f.attrs["damaged_tail"] = problem
    g = f.create_group("channels")
    packed = COMPRESSION if ch["t"].size else {}  # an empty dataset cannot be chunked
    for name, values in ch.items():
        ds = g.create_dataset(name, data=values, **packed)
        unit = units.get(name)  # a hostile descriptor may hold anything there
        ds.attrs["units"] = unit if isinstance(unit, str) else ""
        ds.attrs["description"] = records.DESCRIPTIONS.get(name, "")
    time = g["t"]
    time.make_scale("time")
    for name in ch:
        if name != "t":
            g[name].dims[0].attach_scale(time)
            g[name].dims[0].label = "time"
    g["force"] = g["excitation"]  # hard link: the analysis name of the exogenous force
    r = f.create_group("records")
    r["start"] = _json(start)
    r["descriptor"] = _json(desc)
    r["stop"] = _json(stop)
    r["events"] = _json(events)


def export_csv(session_path, out_path, force: bool = False, warn=None) -> Path:
    """Write the analysis CSV (``# key=value`` lines, header, columns); returns its path.

    An existing ``out_path`` is replaced only with ``force`` (``labbench.safe_write``).
    """
    out = output_path(out_path, [session_path], force)  # before the work
    start, desc, ch, _events, _stop, _problem = load_session(session_path, warn, need_start=True)
    meta = analysis_meta(start, desc)
    table = {"force": ch["excitation"], **ch}
    cols = np.column_stack([np.asarray(table[c], dtype=float) for c in CSV_COLUMNS])
    fmt = ["%d" if np.asarray(table[c]).dtype.kind in "iub" else "%.17g" for c in CSV_COLUMNS]
    header = "".join(f"# {k}={one_line(v)}\n" for k, v in meta.items()) + ",".join(CSV_COLUMNS)
    with replacing(out, [session_path], force) as tmp:  # a refused write: one UserError
        np.savetxt(tmp, cols, delimiter=",", fmt=fmt, header=header, comments="")
    return out


# columns of a frequency-response CSV: name, unit, what
FR_COLUMNS = (("w_rad_s", "rad/s", "angular frequency"), ("f_hz", "Hz", "frequency"),
              ("Z_re", "N s/m", "Re Z, Z = F/(jw X)"), ("Z_im", "N s/m", "Im Z"),
              ("Z_err", "N s/m", "95 % radius of Z"), ("coherence", "1", "coherence"),
              ("low_coherence", "1", "1 where coherence < 0.8"),
              ("ES", "N/m", "effective stiffness"), ("ED", "N s/m", "effective damping"),
              ("EM", "kg", "effective mass"))


def export_frequency_response(fr, out_path, inputs=(), force: bool = False) -> Path:
    """Write a ``labbench.session_api.FrequencyResponse`` as CSV (module doc); returns the path."""
    out = output_path(out_path, inputs, force)
    d = fr.as_dict()
    w = np.asarray(d["w"], float)
    cols = {"w_rad_s": w, "f_hz": w / (2 * np.pi), "Z_re": d["Z_re"], "Z_im": d["Z_im"],
            "Z_err": d["Z_err"], "coherence": d["coherence"],
            "low_coherence": np.asarray(d["low_coherence"], int),
            "ES": d["ES"], "ED": d["ED"], "EM": d["EM"]}
    names = [c[0] for c in FR_COLUMNS]
    meta = {"estimator": d["estimator"], "source": fr.source,
            "ws_star_rad_s": d["ws_star"], "wb_star_rad_s": d["wb_star"]}
    if "theory" in d:
        th = d["theory"]
        cols.update(Z_theory_re=th["Z_re"], Z_theory_im=th["Z_im"])
        names += ["Z_theory_re", "Z_theory_im"]
        meta.update(theory_model=th["model"], theory_m_kg=th["plant"]["m"],
                    theory_b_Ns_per_m=th["plant"]["b"])
    units = {c[0]: c[1] for c in FR_COLUMNS} | {"Z_theory_re": "N s/m", "Z_theory_im": "N s/m"}
    meta["units"] = " ".join(f"{n}[{units[n]}]" for n in names)
    table = np.column_stack([np.asarray(cols[n], float) for n in names])
    fmt = ["%d" if n == "low_coherence" else "%.17g" for n in names]
    header = "".join(f"# {k}={one_line(v)}\n" for k, v in meta.items()) + ",".join(names)
    with replacing(out, inputs, force) as tmp:
        np.savetxt(tmp, table, delimiter=",", fmt=fmt, header=header, comments="")
    return out
