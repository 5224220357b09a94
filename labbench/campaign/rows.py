"""One row per campaign point, in a sweep table's format (``labbench.sweep.table``), with the
exact sampled theory's prediction beside the measurement.

Every row holds ``key``, ``index``, the point's case labels and parameters,
``params_json``, ``status`` (``ok``; ``failed``: the run ended on a safety trip it did not
expect, or its analysis failed; ``skipped``: the pre-check called the point unstable;
``refused``: the runner refused it, e.g. once the device declared a delay), ``error``,
``session``, ``attempts`` (runs the point took: an interrupted one is run again) and
``earlier_sessions``; the protocol's results flattened (``res.*``, as a sweep's); the
verdict; and what the literature asks a Z-width to state, for every point:

* ``rig.loop_rate_hz`` / ``rig.sample_time_s``, ``rig.metres_per_count`` and
  ``rig.counts_per_rev`` (encoder resolution), ``rig.force_limit_n``,
  ``rig.device_delay_s`` and its origin (the delay the run used: its start record);
* ``ve.K``, ``ve.B``, ``ve.w0_rad_s`` (the velocity filter; None: none), ``ve.td_s``;
* ``plant.m``, ``plant.b`` (the physical damping), ``plant.from``;
* ``commission.coulomb_n`` (the rig's last commissioning's Coulomb estimate; None when
  none was found or it fitted none) and ``commission.session``;
* ``max_command_n`` (the largest |force| commanded, from the recording) and ``device_s``.

Predictions (``pred.*``), with the campaign's plant and the run's device delay:

* every VE with a spring: ``pred.k_max`` (exact sampled, ``labbench.model.linear.k_max``) and
  ``pred.k_max_approx`` (the paper's), ``pred.k_passive`` (the sampled-data passivity bound
  of Colgate & Schenkel for this VE, ``labbench.model.passivity``), ``pred.k_passive_line``
  (their b > K T / 2 + |B|) and ``pred.k_passive_quantised`` (Abbott & Okamura's
  2 f_c / Delta with the commissioning's f_c);
* the stability probe: ``zw.k_max`` (measured), ``zw.ci_lo`` / ``zw.ci_hi`` (its 95 %
  interval; with friction the bracket of a stable and an unstable step), ``zw.k_max_above``
  (when no step grew: the stiffest step that rendered, a lower bound), ``zw.rel_error``
  (against ``pred.k_max``), ``zw.observer_k`` (the first step in which the passivity
  observer saw the VE generate energy), ``zw.crossed`` (the bounds the device certainly
  went beyond: below the low end of the interval, or below the lower bound
  ``zw.k_max_above``) and ``zw.stopped`` (where the probe stopped and why: the reason a
  point has no measured boundary);
* with the device's Coulomb friction known (the chirp-ID's that gave the plant, else the
  commissioning's, passed to the probe as
  ``plant_coulomb_n``): ``pred.k_max_friction`` (the friction-aware boundary at the swing
  the probe's pulses were planned to give, ``labbench.model.stability_friction``) and
  ``pred.k_max_friction_plan`` (what it follows from, as JSON: the friction believed,
  ``friction_cap`` and the pulse plan, ``labbench.model.pulse``; the chart draws it over B
  from these), and from
  the run ``zw.k_friction`` (the same at the swing the steps near the boundary started
  from, ``zw.swing_m``) with ``zw.k_friction_lo`` / ``zw.k_friction_hi`` (its range over
  those steps, widened by its tolerance f_c / (K X)), ``zw.rel_error_friction`` (measured
  against it) and ``zw.friction_agrees`` (the range meets the measured interval);
* ETFE: the rendering error against the designed impedance, Z_ideal = (m s^2 + (b + B) s
  + K) / s (no sampling, delay or filter), over the accuracy band 2-100 rad/s:
  ``acc.es_median`` / ``acc.es_max`` of |ES - (K - m w^2)| / K and ``acc.ed_median`` /
  ``acc.ed_max`` of |ED - (b + B)| / (b + B), measured (from the ETFE) and predicted
  (``pred.es_median``, ...: the same of the exact sampled Z); ``acc.es_band`` /
  ``acc.ed_band``: the median 95 % half-width of the measurement in the same units
  (the ETFE's own radius, |dES| <= w |dZ|, |dED| <= |dZ|); ``acc.es_in_band`` /
  ``acc.ed_in_band``: the share of the band's frequencies at which the measured ES (ED)
  lies within that half-width of the predicted one; ``acc.k_max_fit``: K_max of the plant
  and delay the closed-loop fit found (``labbench.analysis.loopfit``), beside ``pred.k_max``;
  ``pred.noise_command``: the force noise the loop commands in the felt band, predicted by
  ``labbench.model.noise`` with the encoder step and amplifier noise the rig states
  (``pred.noise_quantum_m``, ``pred.noise_amplifier_n``) and the Coulomb friction known
  before the run (``pred.noise_coulomb_n``: the run's given or simulated one, else the
  commissioning's; its noise under the run's own excitation, ``pred.noise_stick_share`` the
  share of reversals that stick), beside the measured ``res.force_noise.rms_n`` and its
  interval ``res.force_noise.ci95``.
"""
from __future__ import annotations

import json
import math

import numpy as np

from labbench.model import device_delay
from labbench.model import linear
from labbench.model import passivity
from labbench.errors import UserError
from labbench.sweep.point import flatten, typed_row, verdict_columns
from labbench.model.ve import Plant


def base_row(pp, context) -> dict:
    """The columns every row has (module doc), before the run."""
    p = pp.point
    ve = pp.protocol.ve
    rig = pp.rig
    plant = _plant(pp, context)
    return {
        "key": pp.key, "index": p.index, **p.tags, **p.params,
        "params_json": json.dumps({"params": p.params, "tags": p.tags}, sort_keys=True),
        "status": "ok", "error": None, "session": None, "attempts": 0, "earlier_sessions": None,
        "device": context.device, "rig.name": rig.name,
        "rig.sample_time_s": rig.sample_time_s, "rig.loop_rate_hz": 1.0 / rig.sample_time_s,
        "rig.metres_per_count": rig.metres_per_count, "rig.counts_per_rev": rig.counts_per_rev,
        "rig.force_limit_n": rig.force_limit_n,
        "ve.kind": ve.kind, "ve.K": ve.K, "ve.B": ve.B,
        "ve.w0_rad_s": ve.w0 if math.isfinite(ve.w0) else None, "ve.td_s": ve.td,
        "plant.m": plant.m, "plant.b": plant.b, "plant.from": context.plant_label,
        "commission.coulomb_n": context.commission.get("coulomb_n"),
        "commission.session": context.commission.get("session"),
    }


def skipped_row(pp, context) -> dict:
    delay = device_delay.resolve(pp.rig)
    row = {**base_row(pp, context), "status": "skipped", "error": pp.skipped,
           "rig.device_delay_s": delay.s, "rig.device_delay_origin": delay.origin}
    row.update(predictions(pp, context, {}, delay.s))
    return typed_row(row)


def run_row(pp, context, result, session, start: dict | None, max_command_n: float | None,
            earlier: list[str], wall_s: float) -> dict:
    """The row of a point that ran to its end (success, or a failure that is its result)."""
    delay = device_delay.from_start(start) if start else device_delay.resolve(pp.rig)
    row = base_row(pp, context)
    results = result.results or {}
    row.update(session=str(session) if session else None, attempts=len(earlier) + 1,
               earlier_sessions="; ".join(earlier) or None,
               **{"rig.device_delay_s": delay.s, "rig.device_delay_origin": delay.origin})
    if result.status != "success":
        row.update(status="failed", error=f"run {result.status}: {result.reason}")
    elif "error" in results:
        row.update(status="failed", error=str(results["error"]))
    row.update(n_samples=int(result.n_samples), device_s=result.n_samples * pp.rig.sample_time_s,
               wall_s=wall_s, loop_s=float(result.timing.get("wall_s") or 0.0),
               max_command_n=max_command_n)
    row.update(flatten(results, "res."))
    row.update(verdict_columns(results))
    row.update(predictions(pp, context, results, delay.s))
    return typed_row(row)


def _plant(pp, context) -> Plant:
    o = pp.options
    return Plant(o.get("plant_m_kg", context.plant.m), o.get("plant_b", context.plant.b))


def predictions(pp, context, results: dict, latency: float) -> dict:
    """``pred.*``, ``zw.*`` and ``acc.*`` of one point (module doc)."""
    plant = _plant(pp, context)
    ve = pp.protocol.ve
    out = {}
    if ve.kind in ("spring", "spring-damper"):
        out["pred.k_max"] = linear.k_max(plant, ve, latency=latency)
        out["pred.k_max_approx"] = linear.k_max_approx(plant, ve, latency)
        out["pred.k_passive"] = passivity.passive_k_max(plant, ve, latency)
        out["pred.k_passive_line"] = passivity.colgate_line(plant.b, ve.B, ve.T)
        out["pred.k_passive_quantised"] = passivity.quantisation_bound(
            context.commission.get("coulomb_n"), pp.rig.metres_per_count)
        planned = getattr(pp.protocol, "k_friction", None)
        out["pred.k_max_friction"] = planned(plant) if planned else None
        basis = getattr(pp.protocol, "friction_plan", None)
        basis = basis() if basis else None
        out["pred.k_max_friction_plan"] = json.dumps(basis, sort_keys=True) if basis else None
    if results.get("variable") == "K":
        out.update(_zwidth(results, out))
        out.update(_friction(results))
    if isinstance(results.get("etfe"), dict):
        out.update(_accuracy(results, plant, ve, latency, out.get("pred.k_max")))
    if pp.protocol_name == "etfe" and ve.kind != "none":
        out.update(_noise(pp, context, results, plant, ve, latency))
    return out


def _noise(pp, context, results: dict, plant: Plant, ve, latency: float) -> dict:
    """``pred.noise_command`` [N rms, felt band] of the noise model with the noise sources the
    rig states (``labbench.design.tradeoffs.rig_noise``) and the friction known before the run (module
    doc) under the run's excitation, beside the run's ``res.force_noise.*``."""
    from dataclasses import replace

    from labbench.design.tradeoffs import rig_noise
    from labbench.model import noise

    sources, _ = rig_noise(pp.rig, context.simulated, pp.device_options)
    known = results.get("friction") if isinstance(results.get("friction"), dict) else {}
    fc = known.get("n") if known.get("origin") in ("given", "device") else \
        context.commission.get("coulomb_n")
    c = pp.protocol.config
    excitation = noise.Excitation(c.std_n, None if (c.band_lo_hz == 0 and c.band_hi_hz is None)
                                  else (c.band_lo_hz, c.band_hi_hz or 0.5 / ve.T))
    out = {"pred.noise_command": None, "pred.noise_quantum_m": sources.quantum_m,
           "pred.noise_amplifier_n": sources.force_noise_n, "pred.noise_coulomb_n": fc or None,
           "pred.noise_stick_share": None}
    try:
        fn = noise.force_noise(plant, ve, replace(sources, coulomb_n=fc or 0.0),
                               noise.FELT_BAND_HZ, latency, excitation=excitation)
    except UserError:  # unstable on the campaign's plant, or friction holds the handle
        return out
    out.update({"pred.noise_command": fn.rms_command,
                "pred.noise_stick_share": fn.friction.stick_share if fn.friction else None})
    return out


BOUNDS = (("pred.k_passive", "passive (sampled-data)"),
          ("pred.k_passive_quantised", "passive (quantisation and friction)"),
          ("pred.k_max", "stable (exact sampled)"))


def _zwidth(res: dict, pred: dict) -> dict:
    k = res.get("measured_boundary")
    ci = res.get("measured_ci95") or [None, None]
    steps = [s for s in res.get("steps") or [] if s.get("rendered", True)]
    # no step grew (friction, a ceiling below the device's boundary): K_max is above them all
    above = max((s["K"] for s in steps), default=None) \
        if k is None and steps and not any(s["unstable"] for s in steps) else None
    # what the device certainly reached: the interval's low end, or the lower bound
    level = (ci[0] if ci[0] is not None else k) if k is not None else above
    exact = pred.get("pred.k_max")
    crossed = [name for col, name in BOUNDS
               if level is not None and pred.get(col) is not None and level > pred[col]]
    return {"zw.k_max": k, "zw.ci_lo": ci[0], "zw.ci_hi": ci[1], "zw.k_max_above": above,
            "zw.rel_error": None if k is None or not exact else k / exact - 1,
            "zw.observer_k": (res.get("energy") or {}).get("first_generating"),
            "zw.crossed": "; ".join(crossed) if level is not None else None,
            "zw.stopped": res.get("stopped")}


def _friction(res: dict) -> dict:
    """The friction-aware comparison of a probe that knew the device's friction (module
    doc); None columns otherwise."""
    f = res.get("friction") if isinstance(res.get("friction"), dict) else {}
    rng, tol = f.get("k_range"), f.get("tolerance") or 0.0
    lo, hi = (rng[0] * (1 - tol), rng[1] * (1 + tol)) if rng else (None, None)
    return {"zw.k_friction": f.get("k_max"), "zw.k_friction_lo": lo, "zw.k_friction_hi": hi,
            "zw.swing_m": f.get("swing_m"), "zw.rel_error_friction": f.get("rel_error"),
            "zw.friction_agrees": f.get("agrees")}


def _accuracy(res: dict, plant: Plant, ve, latency: float, k_pred) -> dict:
    from labbench.analysis.etfe import W_BAND
    from labbench.model.effective import effective_impedances

    e = res["etfe"]
    if not all(k in e for k in ("w", "Z_re", "Z_im", "Z_err")):
        return {}
    w = np.asarray(e["w"], float)
    sel = (w >= W_BAND[0]) & (w <= W_BAND[1])
    if not sel.any():
        return {}
    w = w[sel]
    Z = np.asarray(e["Z_re"], float)[sel] + 1j * np.asarray(e["Z_im"], float)[sel]
    radius = np.asarray(e["Z_err"], float)[sel]
    measured = effective_impedances(w, Z)
    predicted = effective_impedances(w, linear.z_sampled(plant, ve, w, latency))
    es_ideal, ed_ideal = ve.K - plant.m * w**2, plant.b + ve.B
    out = {}
    for name, ideal, scale, meas, pred, band in (
            ("es", es_ideal, ve.K, measured.ES, predicted.ES, w * radius),
            ("ed", ed_ideal, ed_ideal, measured.ED, predicted.ED, radius)):
        if not scale:
            continue
        em, ep = np.abs(meas - ideal) / scale, np.abs(pred - ideal) / scale
        out.update({f"acc.{name}_median": float(np.median(em)), f"acc.{name}_max": float(em.max()),
                    f"pred.{name}_median": float(np.median(ep)), f"pred.{name}_max": float(ep.max()),
                    f"acc.{name}_band": float(np.median(band / scale)),
                    f"acc.{name}_in_band": float(np.mean(np.abs(meas - pred) <= band))})
    fit = res.get("loop_fit") or {}
    if k_pred is not None and all(isinstance(fit.get(k), (int, float)) for k in ("m", "b", "td_s")):
        try:
            out["acc.k_max_fit"] = linear.k_max(Plant(fit["m"], fit["b"]), ve,
                                                latency=max(fit["td_s"], 0.0))
        except UserError:  # a fit outside the physical range (b < 0): no plant, no K_max
            out["acc.k_max_fit"] = None
    return out
