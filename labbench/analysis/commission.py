"""Commissioning analysis: is the rig file true? (issue 20; ``labbench run commission``).

One open-loop record (VE off): force doublets of both signs, then a short chirp. From it:

* **direction**: each doublet (+A, -A or -A, +A for ``width`` each) leaves the free
  mass-damper displaced by about ``s A width^2 / m`` (s the sign of its first half):
  positions that move against the force's sign mean the encoder (or the torque) is
  flipped; the rest is analysed with the position negated;
* **delay, mass, damping, friction**: the record fitted with the exact sampled model of
  the device, ``f = m x'' + b x' [+ Fc sign(x')] [+ f0]`` with the held command delayed
  by L (``labbench.analysis.compare.plant_force``: the split of ``labbench.model.linear``),
  the terms chosen as ``analyze id`` chooses them (``labbench.analysis.identify``), L
  the minimiser of the residual; its interval from the residual's curvature with the
  residual's own bandwidth (2 f_c samples a second are independent);
* **scale**: a position read k times too large gives a mass k times too small
  (m x_true'' = F, x = k x_true); a lever arm believed c times the true one scales the
  position by c and, when the command is a torque through the lever arm, the force by c
  as well: mass off by c^-2 (by c^-1 when the force is set at the handle). So
  m / m_nominal = rho implies counts_per_rev / rho, or lever_arm_m rho^(1/e) (e = 2, or 1);
* **the stiffest safe spring**: ``labbench.model.linear.k_max`` with the measured m, b, L.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.optimize import minimize_scalar

from labbench.model import linear
from labbench.analysis.compare import plant_force
from labbench.analysis.dataio import recording_from_arrays
from labbench.analysis.identify import identify
from labbench.readout.verdict import DOUBTFUL, FAILED, OK, from_dict, judge, worst
from labbench.model.ve import Plant, VirtualEnvironment

SCALE_TOL = 0.05  # |m / m_nominal - 1| above this: the rig's scale (or its nominal model) is off
DELAY_TOL_SAMPLES = 0.2  # measured delay this far from the stated one: the rig file is wrong
MAX_DELAY_SAMPLES = 6.0  # the delay searched over [0, this] samples


def direction(t, force, position, doublets) -> dict:
    """Sign of the response to each doublet (list of (start, stop, first sign) indices)."""
    x = np.asarray(position, float)
    moves = [float(sign * (x[min(stop, len(x) - 1)] - x[start])) for start, stop, sign in doublets]
    agree = sum(m > 0 for m in moves)
    flipped = agree < len(moves) / 2
    return {"moves_m": moves, "agree": agree, "of": len(moves), "flipped": bool(flipped)}


def _fit(t, u, x, meta, latency, model):
    rec = recording_from_arrays(t, plant_force(recording_from_arrays(t, u, x, meta), None, latency),
                                x, meta)
    return identify(rec, model=model, hold="zoh")


def delay_and_plant(t, force, position, meta, T) -> dict:
    """L, m, b (and friction terms) of the exact sampled model fitted to the record."""
    u, x = np.asarray(force, float), np.asarray(position, float)
    first = _fit(t, u, x, meta, 0.0, "auto")
    model = first.model
    grid = np.arange(0.0, MAX_DELAY_SAMPLES + 1e-9, 0.25)
    rss = [(_fit(t, u, x, meta, g * T, model).rms_residual, g) for g in grid]
    g0 = min(rss)[1]
    lo, hi = max(0.0, g0 - 0.25), min(MAX_DELAY_SAMPLES, g0 + 0.25)
    best = minimize_scalar(lambda g: _fit(t, u, x, meta, g * T, model).rms_residual ** 2,
                           bounds=(lo, hi), method="bounded", options={"xatol": 1e-3})
    g = float(best.x)
    fit = _fit(t, u, x, meta, g * T, _reselect(t, u, x, meta, g * T))
    # interval: RSS(g) ~ RSS_min (1 + (g - g*)^2 / (n_eff s^2)) with n_eff independent samples
    h = 0.05
    r0, rp, rm = (_fit(t, u, x, meta, v * T, fit.model).rms_residual ** 2 for v in (g, g + h, max(g - h, 0)))
    curv = (rp - 2 * r0 + rm) / h**2
    n_eff = max(2 * fit.cutoff_hz * len(u) * T, 1.0)
    half = 1.96 * math.sqrt(2 * r0 / (n_eff * curv)) if curv > 0 else math.inf
    return {"delay_samples": g, "delay_s": g * T, "delay_ci_samples": [g - half, g + half],
            "fit": fit.as_dict()}


def _interval(ci) -> str:
    return f"[{ci[0]:.3g}, {ci[1]:.3g}]" if ci else ""


def _reselect(t, u, x, meta, latency) -> str:
    """The model ``analyze id`` would choose on the record with the measured delay."""
    return _fit(t, u, x, meta, latency, "auto").model


CHECKS = ("direction", "delay", "scale", "friction", "k_max")


def analyze(t, force, position, doublets, meta: dict) -> dict:
    """Every check (module doc) with its verdict, and the rig changes they call for.

    ``meta``: ``T``, ``nominal`` {m, b}, ``device_delay_s`` (the delay the run assumed),
    ``rig`` {counts_per_rev, lever_arm_m, position_sign}, ``force_via_lever`` (bool).
    """
    T = float(meta["T"])
    rig = meta["rig"]
    nominal = meta["nominal"]
    out: dict = {"changes": {}}
    d = direction(t, force, position, doublets)
    sign = -1.0 if d["flipped"] else 1.0
    if d["flipped"]:
        fix = -int(rig.get("position_sign", 1))
        out["changes"]["position_sign"] = fix
        d["verdict"] = judge([(FAILED, f"the handle moved against the force in {d['of'] - d['agree']} "
                                       f"of {d['of']} pulses: the position (or torque) sign is flipped; "
                                       f"set [rig] position_sign = {fix} (or the drive's polarity)")]).as_dict()
    else:
        d["verdict"] = judge([(OK, "")]).as_dict()
    out["direction"] = d
    fit_meta = {"fs": 1.0 / T, "force_hold": "zoh"}
    dp = delay_and_plant(t, force, sign * np.asarray(position, float), fit_meta, T)
    fit = dp["fit"]
    stated = float(meta.get("device_delay_s") or 0.0)
    dp["stated_s"] = stated
    off = dp["delay_s"] - stated
    ci = dp["delay_ci_samples"]
    if abs(off) > DELAY_TOL_SAMPLES * T:
        out["changes"]["measured_td_s"] = round(dp["delay_s"], 9)
        finding = (FAILED, f"device delay {dp['delay_samples']:.2f} samples "
                           f"[{ci[0]:.2f}, {ci[1]:.2f}], the rig states {stated / T:.2f}: set "
                           f"[rig] measured_td_s = {dp['delay_s']:.6g}")
    elif ci[1] - ci[0] > 1.0:
        finding = (DOUBTFUL, f"device delay interval [{ci[0]:.2f}, {ci[1]:.2f}] samples is wide")
    else:
        finding = (OK, "")
    dp["verdict"] = judge([finding]).as_dict()
    out["delay"] = dp
    rho = fit["m"] / nominal["m"]
    e = 2 if meta.get("force_via_lever", True) else 1
    scale = {"m": fit["m"], "b": fit["b"], "m_ratio": rho,
             "b_ratio": fit["b"] / nominal["b"] if nominal["b"] else None,
             "counts_per_rev_if_encoder": rig["counts_per_rev"] / rho,
             "lever_arm_m_if_lever": rig["lever_arm_m"] * rho ** (1.0 / e)}
    if abs(rho - 1) > SCALE_TOL:
        scale["verdict"] = judge([(FAILED, f"mass {fit['m']:.4g} kg is {rho:.3f} x the nominal "
                                           f"{nominal['m']:.4g} kg: the position scale is off; "
                                           f"counts_per_rev = {scale['counts_per_rev_if_encoder']:.6g} "
                                           f"if the encoder is wrong, lever_arm_m = "
                                           f"{scale['lever_arm_m_if_lever']:.6g} if the lever arm is")]).as_dict()
    else:
        scale["verdict"] = judge([(OK, "")]).as_dict()
    out["scale"] = scale
    ci95 = fit.get("ci95") or {}
    friction = {"model": fit["model"], "coulomb_n": fit.get("coulomb"), "offset_n": fit.get("offset"),
                "ci95": {k: v for k, v in ci95.items() if k in ("coulomb", "offset")},
                "reason": (fit.get("selection") or {}).get("reason")}
    fc = fit.get("coulomb")
    friction["verdict"] = judge([(DOUBTFUL, f"Coulomb friction {fc:.3g} N "
                                            f"{_interval(ci95.get('coulomb'))} (model {fit['model']}): "
                                            "identify with it (analyze id chooses it) and expect a "
                                            "dead band of Fc / K in a spring") if fc else (OK, ""),
                                 (DOUBTFUL, f"force offset {fit['offset']:.3g} N") if fit.get("offset")
                                 else (OK, "")]).as_dict()
    out["friction"] = friction
    plant = Plant(max(fit["m"], 1e-9), max(fit["b"], 0.0))
    spring = VirtualEnvironment("spring", K=1.0, T=T)
    km = linear.k_max(plant, spring, latency=dp["delay_s"])
    out["k_max"] = {"k_max_n_m": km, "m": plant.m, "b": plant.b, "latency_s": dp["delay_s"],
                    "verdict": judge([(OK, "")] if km and km > 0 else
                                     [(FAILED, "no spring is stable on this device")]).as_dict()}
    out["verdict"] = worst(from_dict(out[c]["verdict"]) for c in CHECKS).as_dict()
    return out
