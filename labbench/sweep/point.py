"""One point of a sweep: spec + point in, one row out (a pure function: what a worker runs).

Kind "run": the point's parameters are routed by name (``route``) to the
protocol's config, the rig and the simulated device, and the protocol runs on
the simulator through ``labbench.runner.run``, unpaced, exactly as
``labbench run ... --device sim`` runs it, analysis included. Kind
"analysis": an exact record (``labbench.sweep.exact``) with the point's
measurement errors goes through one analysis (ETFE or identification).

Every row holds the point's parameters (own names), its tags (case labels),
the protocol's results flattened (``res.*``: scalars only, arrays dropped),
what the exact theory says of the point's truth (``truth.*``: the simulated
plant and device delay, whatever the protocol was told) and the measured
results' errors against it, the verdict when the results carry one, the
times (``wall_s``, ``loop_s``, ``analysis_s``: measurements of the machine,
the only columns that differ between two computations of a point), and
``status`` / ``error``: a point that fails is a row saying why, never a
failed sweep.
"""
from __future__ import annotations

import functools
import json
import math
import time
from dataclasses import fields

import numpy as np

from labbench.errors import UserError

# Parameters the sweep itself reads (the rest go to the protocol, the rig or the device).
DEVICE_DELAY = "device_delay_s"  # the simulator's delay on the whole command [s]
K_FRACTION = "K_frac_k_max"  # K as a fraction of the exact K_max of the point's VE
TIME_COLUMNS = ("wall_s", "loop_s", "analysis_s")
LEVELS = ("ok", "doubtful", "failed")
MAX_LIST_ITEMS = 4  # a list of up to this many numbers becomes columns .0, .1, ...


def compute_row(spec: dict, point: dict, keep_dir: str | None = None) -> dict:
    """The row of ``point`` (``{"index", "params", "tags"}``) of ``spec`` (``Spec.as_dict()``).

    ``keep_dir``: record the run's session there (kind run). Never raises for a
    point's own failure: the row's ``status`` ("ok", "refused", "failed", "error") and
    ``error`` say what happened.
    """
    from labbench.sweep.spec import point_key, spec_from_dict

    s = spec_from_dict(spec) if not hasattr(spec, "target") else spec
    params, tags = dict(point["params"]), dict(point.get("tags", {}))
    row = {"key": point_key(s.target, params, tags), "index": int(point["index"]), **tags,
           **params, "params_json": json.dumps({"params": params, "tags": tags}, sort_keys=True),
           "status": "ok", "error": None, "session": None}
    t0 = time.perf_counter()
    try:
        if s.kind == "run":
            row.update(_run_point(s, params, keep_dir))
        else:
            row.update(_analysis_point(s, params))
    except UserError as exc:
        row.update(status="refused", error=str(exc))
    except Exception as exc:  # noqa: BLE001 - one point's bug is its row, not the sweep's end
        row.update(status="error", error=f"{type(exc).__name__}: {exc}")
    row["wall_s"] = time.perf_counter() - t0
    return typed_row(row)


# ----------------------------------------------------------------------------- kind run
def route(protocol: str, params: dict) -> dict:
    """Split a run point's parameters: ``{"protocol", "rig", "device", "sweep"}``.

    ``sample_time_s`` goes to the rig and the protocol; ``seed`` to the protocol (when
    it has one) and the device; ``m``, ``b`` to the device (the simulated plant) and, unless
    given, to the rig's nominal plant (so the theory knows the truth);
    ``device_delay_s`` and ``K_frac_k_max`` to the sweep; the rig's own fields to the
    rig; everything else to the device, which refuses what it does not know.
    """
    from labbench.registry import protocol_class
    from labbench.rig import Rig

    proto = {f.name for f in fields(protocol_class(protocol).Config)}
    rig_fields = set(Rig.__dataclass_fields__) - {"sections", "source", "position_limits_m"}
    out = {"protocol": {}, "rig": {}, "device": {}, "sweep": {}}
    for k, v in params.items():
        if k in (DEVICE_DELAY, K_FRACTION):
            out["sweep"][k] = v
            continue
        if k in proto:
            out["protocol"][k] = v
        if k in rig_fields:
            out["rig"][k] = v
        if k == "seed" or not (k in proto or k in rig_fields):
            out["device"][k] = v
    return out


def build_run(spec, params: dict):
    """The point's (rig, protocol, device options, truth) from its parameters (``route``)."""
    from labbench.model import linear
    from labbench.registry import make_protocol
    from labbench.rig import rig_from_dict
    from labbench.model.ve import DEFAULT_PLANT, Plant

    r = route(spec.protocol, params)
    if "K" in params and K_FRACTION in params:
        raise UserError(f"give K or {K_FRACTION}, not both")
    dev = dict(r["device"])
    rig_t = dict(r["rig"])
    m = float(dev.get("m", rig_t.get("nominal_mass_kg", DEFAULT_PLANT.m)))
    b = float(dev.get("b", rig_t.get("nominal_damping_ns_m", DEFAULT_PLANT.b)))
    rig_t.setdefault("nominal_mass_kg", m)
    rig_t.setdefault("nominal_damping_ns_m", b)
    T = float(rig_t.get("sample_time_s", 0.001))
    delay = r["sweep"].get(DEVICE_DELAY)
    if delay is not None:
        if isinstance(delay, bool) or not isinstance(delay, (int, float)) or not 0 <= delay <= 1:
            raise UserError(f"{DEVICE_DELAY} must be a number of seconds in [0, 1], got {delay!r}")
        delay = float(delay)
        if spec.device != "sim":
            raise UserError(f"{DEVICE_DELAY} sets the delay of device sim, not {spec.device}")
        if "extra_delay_samples" in dev or "extra_delay_fraction" in dev:
            raise UserError(f"give {DEVICE_DELAY} or the sim's extra_delay_*, not both")
        whole = math.floor(delay / T + 1e-9)
        frac = delay / T - whole
        dev["extra_delay_samples"] = whole
        if frac > 1e-9:
            dev["extra_delay_fraction"] = frac
        rig_t.setdefault("measured_td_s", delay)  # the analysis knows the device's delay
        rig_t.setdefault("measured_td_from", "labbench sweep: the simulator's delay")
    latency = T * (dev.get("extra_delay_samples", 0) + dev.get("extra_delay_fraction", 0.0))
    rig = rig_from_dict({"rig": rig_t}, source="<sweep point>")
    seed = dev.pop("seed", None)
    plant = Plant(m, b)
    proto_opts = {**r["protocol"], "sample_time_s": rig.sample_time_s}
    if K_FRACTION in r["sweep"]:
        frac = r["sweep"][K_FRACTION]
        if isinstance(frac, bool) or not isinstance(frac, (int, float)) or not frac > 0:
            raise UserError(f"{K_FRACTION} must be a number > 0, got {frac!r}")
        probe = make_protocol(spec.protocol, **{**proto_opts, "K": 1.0})
        k = linear.k_max(plant, probe.ve, latency=latency)
        if k is None:
            raise UserError(f"{K_FRACTION}: the VE has no stable K on this plant")
        proto_opts["K"] = float(frac) * k
    protocol = make_protocol(spec.protocol, **proto_opts)
    if seed is None:
        seed = protocol.seed
    truth = {"m": m, "b": b, "device_delay_s": latency, "plant": plant,
             "coulomb_n": float(dev.get("coulomb_n", 0.0))}
    return rig, protocol, {"seed": seed, **dev}, truth


def _run_point(spec, params: dict, keep_dir) -> dict:
    from labbench.registry import open_device
    from labbench.runner import run, run_recorded

    rig, protocol, dev_opts, truth = build_run(spec, params)
    out = {"K": protocol.config.K} if K_FRACTION in params else {}
    stamps = {}

    def progress(_fraction, message):
        if message == "analysis":
            stamps["analysis"] = time.perf_counter()

    device = open_device(spec.device, rig, **dev_opts)
    t_end = None
    if keep_dir is not None:
        result, path = run_recorded(device, protocol, keep_dir, progress=progress, rig=rig,
                                    simulated=True,
                                    start_extra={"sweep": {"name": spec.name, "params": params}})
        t_end = time.perf_counter()
        out["session"] = str(path) if path else None
    else:
        result = run(device, protocol, [], progress=progress, rig=rig, simulated=True)
        t_end = time.perf_counter()
    results = result.results or {}
    if result.status != "success":
        out.update(status="failed", error=f"run {result.status}: {result.reason}")
    elif "error" in results:
        out.update(status="failed", error=str(results["error"]))
    out["n_samples"] = int(result.n_samples)
    out["loop_s"] = float(result.timing.get("wall_s") or 0.0)
    out["analysis_s"] = t_end - stamps["analysis"] if "analysis" in stamps else None
    out.update(flatten(results, "res."))
    out.update(_truth(protocol.ve, truth, results))
    out.update(verdict_columns(results))
    return out


def _truth(ve, truth: dict, results: dict) -> dict:
    """What the exact sampled theory says of the point's truth, and the results' errors."""
    from labbench.model import linear

    plant, latency = truth["plant"], truth["device_delay_s"]
    out = {"truth.m": truth["m"], "truth.b": truth["b"], "truth.device_delay_s": latency,
           "truth.coulomb_n": truth.get("coulomb_n", 0.0)}
    out["truth.stable"] = bool(linear.stability(plant, ve, latency).stable)
    if ve.kind in ("spring", "spring-damper"):
        out["truth.k_max"] = linear.k_max(plant, ve, latency=latency)
        out["truth.k_max_approx"] = linear.k_max_approx(plant, ve, latency)
    e = results.get("etfe")
    if isinstance(e, dict) and all(k in e for k in ("w", "Z_re", "Z_im")):
        w = np.asarray(e["w"], float)
        Z = np.asarray(e["Z_re"], float) + 1j * np.asarray(e["Z_im"], float)
        out.update(accuracy(w, Z, linear.z_sampled(plant, ve, w, latency)))
        bw = linear.predicted_bandwidths(plant, ve, "sampled", latency)
        out["truth.ws_star"], out["truth.wb_star"] = bw["ws_star"], bw["wb_star"]
    if results.get("variable") == "K" and "truth.k_max" in out:
        out["truth.k_max_rel_error"] = _rel(results.get("measured_boundary"), out["truth.k_max"])
    fit = results.get("loop_fit")
    if isinstance(fit, dict) and "m" in fit:
        out["truth.fit_m_rel"] = _rel(fit["m"], truth["m"])
        out["truth.fit_b_rel"] = _rel(fit["b"], truth["b"])
        if fit.get("b_viscous") is not None:  # friction's part taken out (analysis.friction)
            out["truth.fit_b_viscous_rel"] = _rel(fit["b_viscous"], truth["b"])
    if "identification" in results:
        out.update(_id_errors(results.get("m"), results.get("b"), truth["m"], truth["b"]))
    return out


def accuracy(w, Z, Z_true) -> dict:
    """Median and max |Z - Z_true| / |Z_true| over the accuracy band (labbench.analysis.etfe
    W_BAND, 2-100 rad/s): the columns ``truth.median_rel`` and ``truth.max_rel``."""
    from labbench.analysis.etfe import W_BAND

    sel = (w >= W_BAND[0]) & (w <= W_BAND[1])
    if not sel.any():
        return {"truth.median_rel": None, "truth.max_rel": None}
    err = np.abs(Z[sel] - Z_true[sel]) / np.abs(Z_true[sel])
    return {"truth.median_rel": float(np.median(err)), "truth.max_rel": float(err.max())}


def _id_errors(m, b, m_true: float, b_true: float) -> dict:
    rm, rb = _rel(m, m_true), _rel(b, b_true)
    worst = None if rm is None or rb is None else max(abs(rm), abs(rb))
    return {"truth.m_rel": rm, "truth.b_rel": rb, "truth.worst_rel": worst}


def _rel(a, b):
    return None if a is None or b is None or b == 0 else float(a / b - 1)


# ----------------------------------------------------------------------------- kind analysis
# parameter -> default, per analysis (a name outside these is refused)
ETFE_PARAMS = {"ve": "spring-damper", "K": 50.0, "B": 1.0, "w0_rad_s": 125.0, "td_s": 0.0,
               "sample_time_s": 0.001, "m": 0.094, "b": 0.10, "n": 120000, "record_n": None,
               "seed": 0, "force_std": 1.0, DEVICE_DELAY: 0.0, "process_noise_n": 0.0,
               "quantum_m": 0.0, "position_noise_m": 0.0, "force_noise_rel": 0.0,
               "noise_seed": 0, "estimator": None, "window": 200}
ID_PARAMS = {"n": 60000, "m": 0.094, "b": 0.10, "coulomb_n": 0.0, "amplitude_n": 1.0,
             "f1_hz": 20.0, "force_noise_n": 0.0, "quantum_m": 0.0, "outlier_fraction": 0.0,
             "outlier_size_n": 0.0, "noise_seed": 0, "model": "mb", "method": "l2",
             "solver": "fast", "hold": None}


def analysis_params(analysis: str, params: dict) -> dict:
    """The point's parameters over the analysis' defaults; unknown names refused."""
    from labbench.errors import unknown_name

    known = ETFE_PARAMS if analysis == "etfe" else ID_PARAMS
    for k in params:
        if k not in known:
            raise unknown_name(f"parameter of analysis {analysis}:", k, known)
    return {**known, **params}


@functools.lru_cache(maxsize=4)
def _closed_loop(kind, K, B, w0, T, td, m, b, n, seed, force_std, latency, process_noise):
    from labbench.sweep.exact import closed_loop_recording
    from labbench.model.ve import VirtualEnvironment

    ve = VirtualEnvironment(kind, K, B, w0, T, td)
    return closed_loop_recording(ve, n=n, m=m, b=b, seed=seed, force_std=force_std,
                                 latency=latency, process_noise=process_noise)


@functools.lru_cache(maxsize=4)
def _chirp(n, m, b, coulomb, amp, f1):
    from labbench.sweep.exact import chirp_recording

    return chirp_recording(n=n, m=m, b=b, coulomb=coulomb, amp=amp, f1=f1)


def _analysis_point(spec, params: dict) -> dict:
    p = analysis_params(spec.analysis, params)
    return _etfe_point(p, spec.repeat) if spec.analysis == "etfe" else _id_point(p, spec.repeat)


def _best(fn, repeat: int):
    best, out = math.inf, None
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def _etfe_point(p: dict, repeat: int) -> dict:
    from labbench.analysis.dataio import recording_from_arrays
    from labbench.analysis.etfe import etfe
    from labbench.sweep.exact import measured, z_truth
    from labbench.model.ve import VirtualEnvironment

    w0 = math.inf if p["w0_rad_s"] is None else float(p["w0_rad_s"])
    ve = VirtualEnvironment(p["ve"], float(p["K"]), float(p["B"]), w0, float(p["sample_time_s"]),
                            float(p["td_s"]))
    n = int(p["n"])
    record_n = n if p["record_n"] is None else int(p["record_n"])
    if record_n < n:
        raise UserError(f"record_n ({record_n}) must be at least n ({n})")
    base = _closed_loop(ve.kind, ve.K, ve.B, ve.w0, ve.T, ve.td, float(p["m"]), float(p["b"]),
                        record_n, int(p["seed"]), float(p["force_std"]), float(p[DEVICE_DELAY]),
                        float(p["process_noise_n"]))
    cut = recording_from_arrays(base.t[:n], base.force[:n], base.position[:n], base.meta)
    rec = measured(cut, np.random.default_rng(int(p["noise_seed"])), float(p["quantum_m"]),
                   float(p["position_noise_m"]), float(p["force_noise_rel"]))
    t, res = _best(lambda: etfe(rec, p["estimator"], int(p["window"])), repeat)
    Zt = z_truth(ve, res.w, float(p["m"]), float(p["b"]), float(p[DEVICE_DELAY]))
    flags = sorted({f.split(":")[0] for f in res.flags})
    return {"analysis_s": t, "n_samples": n, "res.estimator": res.estimator,
            "res.flags": "; ".join(flags), "res.flags.n": len(flags),
            **accuracy(np.asarray(res.w), np.asarray(res.Z), Zt)}


def _id_point(p: dict, repeat: int) -> dict:
    from labbench.analysis.identify import identify
    from labbench.sweep.exact import with_noise

    base = _chirp(int(p["n"]), float(p["m"]), float(p["b"]), float(p["coulomb_n"]),
                  float(p["amplitude_n"]), float(p["f1_hz"]))
    rec = with_noise(base, np.random.default_rng(int(p["noise_seed"])),
                     force_noise=float(p["force_noise_n"]), quantum=float(p["quantum_m"]),
                     outlier_fraction=float(p["outlier_fraction"]),
                     outlier_size=float(p["outlier_size_n"]))
    t, res = _best(lambda: identify(rec, model=p["model"], method=p["method"], solver=p["solver"],
                                    hold=p["hold"]), repeat)
    out = {"analysis_s": t, "n_samples": int(p["n"]),
           "res.l1_objective": float(np.sum(np.abs(res.residual)))}
    out.update(flatten(res.as_dict(), "res."))
    out.update(_id_errors(res.m, res.b, float(p["m"]), float(p["b"])))
    return out


# ----------------------------------------------------------------------------- rows
def flatten(d: dict, prefix: str) -> dict:
    """Scalars of a nested results dict as ``prefix + dotted.name`` columns. Arrays and long
    lists are dropped (``.n`` says how long a list was); a list of text (flags) becomes its
    items' names before ':' joined by '; '; a list of up to 4 numbers becomes ``.0``, ``.1``..."""
    out = {}
    for k, v in d.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, name + "."))
        elif isinstance(v, np.ndarray):
            continue
        elif isinstance(v, (list, tuple)):
            out[name + ".n"] = len(v)
            if v and all(isinstance(x, str) for x in v):
                out[name] = "; ".join(x.split(":")[0] for x in v)
            elif 0 < len(v) <= MAX_LIST_ITEMS and all(_is_number(x) for x in v):
                out.update({f"{name}.{i}": x for i, x in enumerate(v)})
        else:
            out[name] = v
    return out


def verdict_columns(results) -> dict:
    """``verdict`` (the worst level of every ``verdict`` dict in the results: ok < doubtful
    < failed) and ``verdict_reasons``; None when no analysis gave one."""
    found = []

    def walk(x):
        if isinstance(x, dict):
            v = x.get("verdict")
            if isinstance(v, dict) and v.get("level") in LEVELS:
                found.append(v)
            for k, y in x.items():
                if k != "verdict":
                    walk(y)

    walk(results)
    if not found:
        return {"verdict": None, "verdict_reasons": None}
    level = max((v["level"] for v in found), key=LEVELS.index)
    reasons = [str(r) for v in found if v["level"] == level for r in v.get("reasons") or []]
    return {"verdict": level, "verdict_reasons": "; ".join(dict.fromkeys(reasons)) or None}


def _is_number(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)


def typed_row(row: dict) -> dict:
    """Column values as the table stores them: numbers float64 (index and counts int64),
    bools, text, None; non-finite numbers None."""
    from labbench.jsonutil import json_safe

    out = {}
    for k, v in row.items():
        v = json_safe(v)
        if _is_number(v) and not (k in ("index", "n_samples") or k.endswith(".n")):
            v = float(v)
        elif not (v is None or isinstance(v, (bool, int, float, str))):
            v = json.dumps(v, sort_keys=True)
        out[k] = v
    return out
