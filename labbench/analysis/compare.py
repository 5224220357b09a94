"""Measured against predicted: the VE named in the metadata, the device (given,
or identified from the closed-loop record itself), the theory curve on the
measured frequencies, and the deviation from it.

Identification from a closed-loop record: the plant sees f_exo[k] - f_ve[k - n]
(docs/conventions.md signs), and f_ve is computed from the sampled position with the
loop's own law (labbench.theory module doc: backward difference, first-order
low-pass at w0, f = K x + B v, n = td / T samples of delay). So m and b come
from the same record, with the same identification as open-loop data.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import signal

from labbench import theory
from labbench.analysis.dataio import Recording, recording_from_arrays
from labbench.analysis.etfe import W_BAND, EtfeResult
from labbench.analysis.identify import IdResult, identify
from labbench.effective import effective_impedances, measured_wb_star
from labbench.errors import UserError
from labbench.ve import VE_KINDS, Plant, VirtualEnvironment


def ve_from_meta(meta: dict, fs: float) -> VirtualEnvironment | None:
    """The VE of the metadata keys ve, K, B, w0, td (None when ``ve`` is absent)."""
    kind = meta.get("ve")
    if kind is None:
        return None
    if kind not in VE_KINDS:
        raise UserError(f"metadata ve={kind!r} is not one of {', '.join(VE_KINDS)}")
    w0 = meta.get("w0")
    no_filter = w0 is None or str(w0).strip().lower() in ("", "none", "null", "inf")
    return VirtualEnvironment(
        kind=kind,
        K=meta_number(meta, "K", 0.0),
        B=meta_number(meta, "B", 0.0),
        w0=math.inf if no_filter else meta_number(meta, "w0"),
        T=1.0 / meta_number(meta, "fs", fs),
        td=meta_number(meta, "td", 0.0),
    )


def meta_number(meta: dict, key: str, default: float | None = None) -> float | None:
    """A numeric metadata value (default when absent); a clear error when it is not a number."""
    value = meta.get(key, default)
    if value is None:
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        raise UserError(f"metadata {key}={value!r} is not a number") from None


def plant_force(rec: Recording, ve: VirtualEnvironment) -> np.ndarray:
    """Force on the plant, f_exo[k] - f_ve[k - n], with f_ve from the sampled position."""
    x = np.asarray(rec.position, float)
    a, T = ve.filter_pole, ve.T
    xp = np.concatenate([[x[0]], x])  # at rest before the record: x[-1] = x[0]
    v = signal.lfilter([(1 - a) / T, -(1 - a) / T], [1.0, -a], xp)[1:]
    f_ve = ve.K * x + ve.B * v
    n = ve.delay_samples if ve.td else 0
    if n:
        f_ve = np.concatenate([np.zeros(n), f_ve[:-n]])
    return np.asarray(rec.force, float) - f_ve


def plant_recording(rec: Recording) -> tuple[Recording, VirtualEnvironment | None]:
    """The record with the force the plant felt: unchanged in open loop, f_exo - f_ve when
    the metadata name a VE. Returns (recording, ve or None)."""
    ve = ve_from_meta(rec.meta, rec.fs)
    if ve is None or ve.kind == "none":
        return rec, None
    u = plant_force(rec, ve)
    return recording_from_arrays(rec.t, u, rec.position, rec.meta, rec.source), ve


def identify_closed_loop(rec: Recording, ve: VirtualEnvironment, method: str = "l2") -> IdResult:
    """m, b from a closed-loop record (see module doc)."""
    u = plant_force(rec, ve)
    return identify(recording_from_arrays(rec.t, u, rec.position, rec.meta, rec.source),
                    model="mb", method=method)


def compare(res: EtfeResult, plant: Plant, ve: VirtualEnvironment, latency: float = 0.0) -> dict:
    """Theory curve at the measured w and the complex relative deviation |Z - Zt| / |Zt|.

    The exact sampled model when td is whole samples, else the paper's eq. 2;
    ``latency`` [s]: the rig's extra loop delay (``labbench.theory`` module doc),
    in the paper's model simply added to td.
    """
    model = "sampled" if theory.whole_samples(ve) else "paper"
    if model == "sampled":
        Zt = theory.z_sampled(plant, ve, res.w, latency)
    else:
        Zt = theory.z_paper(plant, ve.with_(td=ve.td + latency), res.w)
    dev = np.abs(res.Z - Zt) / np.abs(Zt)
    band = (res.w >= W_BAND[0]) & (res.w <= W_BAND[1])
    eff = effective_impedances(res.w, res.Z)
    return {
        "model": model,
        "plant": {"m": plant.m, "b": plant.b},
        "ve": ve.as_dict(),
        "latency_s": latency,
        "Z_theory": Zt,
        "deviation": dev,
        "deviation_median": float(np.median(dev[band])) if band.any() else None,
        "deviation_max": float(np.max(dev[band])) if band.any() else None,
        "band_rad_s": list(W_BAND),
        "wb_star": measured_wb_star(res.w, eff.ED, plant.b),
        "predicted_ws_star": theory.predicted_ws_star(plant, ve),
        "predicted_wb_star": theory.predicted_wb_star(ve),
    }
