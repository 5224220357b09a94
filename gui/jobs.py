"""What the window computes off the GUI thread, and the words it puts on sessions (no Qt).

Each job is a plain function a worker thread runs (``labbench.gui.worker.run_in_background``):
reading the sessions folder, loading a chirp-ID's identification, re-analysing a session
as ``labbench analyze`` does. Results go back to the window through its mailbox.
"""
from __future__ import annotations

from pathlib import Path

from labbench.analysis.compare import ve_from_meta
from labbench.errors import UserError
from labbench.gui.live_estimate import estimate
from labbench.model.predictions import recorded_plant
from labbench.readout.wording import plant_source
from labbench.model.ve import Plant


def plant_data(data: dict, meta: dict) -> dict:
    """The record as the plant felt it: the command force after the device's own delay
    (``labbench.model.device_delay``; ``compare.plant_force``, as chirp-ID's analysis fits it)."""
    from labbench.analysis.compare import plant_force
    from labbench.analysis.dataio import recording_from_arrays
    from labbench.model.device_delay import from_meta

    latency = from_meta(meta)
    if not latency:
        return data
    rec = recording_from_arrays(data["t"], data["command"], data["position"], meta)
    return {**data, "command": plant_force(rec, None, latency)}


def reanalyse_session(path: str, estimator: str | None, run_plant: Plant | None,
                      progress=None, cancel=None):
    """ETFE (with ``estimator``) and identification of a recorded session; runs on a worker.
    ``run_plant`` given: the theory uses the session's own plant (``recorded_plant``), this
    one when it names none; None: the plant identified on the session's data.
    ``progress(fraction, phrase)``, ``cancel`` (a threading.Event: ``Cancelled`` at the
    analyses' next check): as ``labbench.analysis.progress``."""
    from labbench.analysis.progress import Steps
    from labbench.sessions.session_content import load_analysis_arrays, load_session

    steps = Steps(progress, cancel)
    steps.report(0.0, "reading the session")
    arrays = load_analysis_arrays(path)
    start, desc, ch, _ev, stop, _problem = load_session(path)
    meta = arrays["meta"]
    data = {"t": ch["t"], "excitation": ch["excitation"], "position": ch["position"],
            "command": ch["command"]}
    plant, source = None, "identified (l2)"
    if run_plant is not None:
        plant = recorded_plant(start, (stop or {}).get("results"))
        source = plant_source(start) if plant else "the window's rig nominal model"
        plant = plant or run_plant
    again = analyze_etfe(path, estimator, meta, progress=steps.part(0.05, 0.45), cancel=cancel)
    # its w_s*, w_b* are the ones `labbench analyze etfe` says (with the run's plant)
    est = estimate(data, meta, ve_from_meta(meta), plant, estimator=estimator, plant_source=source,
                   progress=steps.part(0.45, 0.7), cancel=cancel,
                   recorded=again.get("bandwidths") if run_plant is not None else None)
    ident = identify_all(data, meta, progress=steps.part(0.7, 1.0), cancel=cancel)
    # not "done": the Sessions line says that once the window shows the results
    steps.report(1.0, "computed, showing")
    return (est, ident, plant_data(data, meta), again,
            (start, desc, ch, stop))  # the record too: the Live page shows its traces


def analyze_etfe(path: str, estimator: str | None, meta: dict, progress=None, cancel=None) -> dict:
    """What ``labbench analyze etfe --fit [--estimator X]`` says of a session with a VE
    (``Session.etfe(fit=True)``): its readout (``labbench.readout.wording``: verdicts, the rendered
    impedance) and the closed-loop fit (or why none); for a session without a VE only its path."""
    from labbench.readout import wording
    from labbench.session_api import load

    out = {"path": path, "options": f"--estimator {estimator} " if estimator else "", "readout": None}
    if ve_from_meta(meta) is None:
        return out
    session = load(path)
    try:
        fr = session.etfe(estimator=estimator, fit=True, progress=progress, cancel=cancel)
        fit = None
    except UserError as exc:  # the fit's failure (or the ETFE's): the ETFE and its verdict still
        fit = {"error": str(exc)}  # show when it stands alone, as `analyze etfe` without --fit
        try:
            fr = session.etfe(estimator=estimator, cancel=cancel)
        except UserError:
            out["fit"] = fit
            return out
    d = fr.as_dict()
    out["fit"] = fit or d["fit"]
    out["bandwidths"] = d.get("bandwidths")
    out["readout"] = wording.of_etfe_analysis(d, session.records.get("start"))
    return out


def catalogue(folder, session_dir, rig_name: str):
    """(the sessions in ``folder``, the newest chirp-ID of ``rig_name`` in ``session_dir``):
    the Sessions tab's rows and the plant the next runs take (``last_identified``)."""
    from labbench.sessions.session_catalogue import last_identified, list_sessions

    summaries = list_sessions(folder) if Path(folder).is_dir() else []
    return summaries, last_identified(session_dir, rig_name, on_skip=lambda *_: None)


def load_identification(path: str):
    """(the identification a chirp-ID session recorded, its data as the plant felt them,
    ``path``)."""
    from labbench.sessions.session_content import analysis_meta, load_session

    start, desc, ch, _ev, stop, _problem = load_session(path)
    ident = ((stop or {}).get("results") or {}).get("identification")
    data = {k: ch[k] for k in ("t", "command", "position") if k in ch}
    return (ident if isinstance(ident, dict) else {}), plant_data(data, analysis_meta(start, desc)), path


def used_method(ident: dict) -> str | None:
    """The fit whose m, b a chirp-ID gives as its result (``protocols.chirp_id``: l2 first)."""
    return "l2" if "l2" in ident else next(iter(ident), None)


def identify_all(data: dict, meta: dict, progress=None, cancel=None) -> dict:
    """l2 and l1 fits of the net force on the device (the ``command`` channel, after the
    device's own delay: as chirp-ID's analysis fits it); a fit the data refuse is
    ``{"error": why}``."""
    from labbench.analysis.dataio import recording_from_arrays
    from labbench.analysis.identify import identify
    from labbench.analysis.progress import Steps

    steps = Steps(progress, cancel)
    felt = plant_data(data, meta)
    rec = recording_from_arrays(felt["t"], felt["command"], felt["position"], meta)
    out = {}
    for i, method in enumerate(("l2", "l1")):
        try:
            out[method] = identify(rec, model="auto", method=method,
                                   progress=steps.part(i / 2, (i + 1) / 2), cancel=cancel).as_dict()
        except UserError as exc:
            out[method] = {"error": str(exc)}
    return out


def timing_preflight(rig, backend: str) -> dict:
    """The timing preflight (``labbench devices --timing``, ``labbench.loop.preflight``) on
    ``backend`` for the rig's ``[preflight] seconds``, in a process of its own as the
    acquisition process runs the loop (away from the window's GIL, whose drawing would be
    measured as the host's stalls). Its JSON; one ``UserError`` (exit 2) or
    ``DeviceError`` line when it refuses or fails."""
    import json
    import subprocess
    import sys

    from labbench.errors import DeviceError
    from labbench.loop.preflight import PreflightConfig

    seconds = PreflightConfig.from_rig(rig).seconds
    argv = [sys.executable, "-m", "labbench", "devices", "--timing", repr(seconds), "--device",
            backend, "--json"]
    if rig.source and Path(str(rig.source)).is_file():
        argv += ["--rig", str(rig.source)]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=seconds + 120)
    if proc.returncode != 0:
        line = (proc.stderr.strip().splitlines() or [f"exit code {proc.returncode}"])[-1]
        line = line.removeprefix("labbench devices: error: ")
        raise (UserError if proc.returncode == 2 else DeviceError)(line)
    return json.loads(proc.stdout)
