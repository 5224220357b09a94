"""Measured against predicted: the VE named in the metadata, the device (given,
or identified from the closed-loop record itself), the theory curve on the
measured frequencies, and the deviation from it.

Identification from a closed-loop record: the plant sees f_exo[k] - f_ve[k - n]
(docs/conventions.md signs), and f_ve is computed from the sampled position with the
loop's own law (labbench.model.linear module doc: backward difference, first-order
low-pass at w0, f = K x + B v, n = td / T samples of delay). So m and b come
from the same record, with the same identification as open-loop data.
"""
from __future__ import annotations

import math

import numpy as np
from scipy import signal

from labbench.model import device_delay
from labbench.model import linear
from labbench.analysis.dataio import Recording, recording_from_arrays
from labbench.analysis.etfe import W_BAND, EtfeResult
from labbench.analysis.identify import IdResult, identify
from labbench.errors import UserError
from labbench.model.ve import VE_KINDS, Plant, VirtualEnvironment


def ve_from_meta(meta: dict, fs: float | None = None) -> VirtualEnvironment | None:
    """The VE of the metadata keys ve, K, B, w0, td, fs (``fs`` when the metadata have
    none; None when ``ve`` is absent or no sample rate is known)."""
    kind = meta.get("ve")
    if kind is None or (fs is None and meta.get("fs") is None):
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


def plant_force(rec: Recording, ve: VirtualEnvironment | None, latency: float = 0.0) -> np.ndarray:
    """Force on the plant: the command f_exo[k] - f_ve[k - n] (f_ve from the sampled
    position; none in open loop) as the plant holds it after the rig's extra delay
    ``latency`` = (d + alpha) T: (1 - alpha) u[k - d] + alpha u[k - d - 1], the two held
    values the split step carries (``labbench.model.linear`` module doc), at rest before the record.

    A VE td that is not whole samples (the paper's continuous delay, docs/analysis.md)
    delays f_ve the same split way: exact for whole samples, the linear interpolation
    of the delayed force otherwise."""
    u = np.asarray(rec.force, float)
    if ve is not None and ve.kind != "none":
        x = np.asarray(rec.position, float)
        a, T = ve.filter_pole, ve.T
        xp = np.concatenate([[x[0]], x])  # at rest before the record: x[-1] = x[0]
        v = signal.lfilter([(1 - a) / T, -(1 - a) / T], [1.0, -a], xp)[1:]
        u = u - _delayed(ve.K * x + ve.B * v, ve.td, T)
    return _delayed(u, latency, rec.T) if latency else u


def _delayed(u: np.ndarray, delay: float, T: float) -> np.ndarray:
    """u delayed by ``delay`` = (d + alpha) T: (1 - alpha) u[k - d] + alpha u[k - d - 1],
    zero before the record."""
    d, alpha = linear.latency_split(delay, T)
    late = np.concatenate([np.zeros(min(d, len(u))), u[: max(len(u) - d, 0)]])
    return (1 - alpha) * late + alpha * np.concatenate([[0.0], late[:-1]]) if alpha else late


def plant_recording(rec: Recording) -> tuple[Recording, VirtualEnvironment | None]:
    """The record with the force the plant felt (``plant_force``, with the metadata's VE and
    device delay, ``labbench.model.device_delay``): unchanged in open loop without a device delay.
    Returns (recording, ve or None)."""
    ve = ve_from_meta(rec.meta, rec.fs)
    if ve is not None and ve.kind == "none":
        ve = None
    latency = device_delay.from_meta(rec.meta)
    if ve is None and not latency:
        return rec, None
    return recording_from_arrays(rec.t, plant_force(rec, ve, latency), rec.position, rec.meta,
                                 rec.source), ve


def identify_closed_loop(rec: Recording, ve: VirtualEnvironment, method: str = "l2",
                         latency: float = 0.0, progress=None, cancel=None, model: str = "mb",
                         coulomb_n: float | None = None) -> IdResult:
    """m, b (and with ``model`` "auto" or "mbc" the Coulomb friction) from a closed-loop
    record (see module doc; ``latency``: the rig's extra delay; ``progress``, ``cancel``:
    ``labbench.analysis.progress``; ``coulomb_n``: a known Coulomb level, taken off the
    force before m, b are fitted, ``identify``)."""
    u = plant_force(rec, ve, latency)
    return identify(recording_from_arrays(rec.t, u, rec.position, rec.meta, rec.source),
                    model=model, method=method, response=loop_response(rec, ve, latency),
                    progress=progress, cancel=cancel, coulomb_n=coulomb_n)


def loop_response(rec: Recording, ve: VirtualEnvironment, latency: float = 0.0):
    """``(m, b) ->`` the position the closed loop of ``ve`` (the device delay ``latency``)
    would have on the record's exogenous force alone: its exact sampled response
    1 / (jw Z) (``linear.z_sampled``, fractional delays too) through the FFT. The
    identification's instruments (``identify``'s ``response``): any function of the
    exogenous force is uncorrelated with the noise; the FFT's wrap-around at the record's
    ends only makes the instruments weaker there."""
    f = np.asarray(rec.force, float)
    w = 2 * np.pi * np.fft.rfftfreq(len(f), rec.T)
    F = np.fft.rfft(f)

    def response(m: float, b: float) -> np.ndarray:
        H = np.zeros(len(w), complex)  # DC left out: the derivatives do not see it
        Z = linear.z_sampled(Plant(m, b), ve.with_(td=0.0), w[1:], latency, ve_delay=ve.td)
        H[1:] = 1.0 / (1j * w[1:] * Z)
        return np.fft.irfft(F * H, len(f))
    return response


def theory_curves(plant: Plant, ve: VirtualEnvironment, w, latency: float = 0.0) -> dict:
    """The theory overlay at w: ``sampled``, the exact sampled model (None when td is not
    whole samples), and ``paper``, eq. 2, both with the device's own delay ``latency``
    [s] (``labbench.model.device_delay``, ``labbench.model.linear.z_paper``); ``model`` and
    ``Z``: the one to compare with, the sampled model when it exists."""
    w = np.asarray(w, float)
    sampled = linear.z_sampled(plant, ve, w, latency) if linear.whole_samples(ve) else None
    paper = linear.z_paper(plant, ve, w, latency)
    model = "sampled" if sampled is not None else "paper"
    return {"model": model, "Z": sampled if sampled is not None else paper, "sampled": sampled, "paper": paper}


def deviation(res: EtfeResult, Zt: np.ndarray, band_rad_s) -> dict:
    """|Z - Zt| / |Zt| over ``band_rad_s``: its median and max, the frequency of the max and
    the estimate's 95 % radius there relative to |Zt| (so a large max reads beside the noise
    of its frequency; not a test: the largest of many errors is often past its own 95 %);
    None where the band holds no frequency."""
    lo, hi = (float(x) for x in band_rad_s)
    sel = np.flatnonzero((res.w >= lo) & (res.w <= hi))
    out = {"band_rad_s": [lo, hi], "n_points": int(sel.size), "median_rel": None, "max_rel": None,
           "max_rad_s": None, "max_band_rel": None}
    if sel.size:
        rel = np.abs(res.Z[sel] - Zt[sel]) / np.abs(Zt[sel])
        i = int(np.argmax(rel))
        out.update(median_rel=float(np.median(rel)), max_rel=float(rel[i]), max_rad_s=float(res.w[sel[i]]),
                   max_band_rel=float(res.Z_err[sel[i]] / np.abs(Zt[sel[i]])))
    return out


def compare(res: EtfeResult, plant: Plant, ve: VirtualEnvironment, latency: float = 0.0,
            band_rad_s: tuple[float, float] | None = None) -> dict:
    """Measured against predicted: the theory curve (``theory_curves``) at the measured w
    and the complex relative deviation |Z - Zt| / |Zt|, its median and max over ``band_rad_s``
    (None: W_BAND), and the paper's closed-form bandwidths. ``Z_paper``: eq. 2 as well, for
    plots."""
    curves = theory_curves(plant, ve, res.w, latency)
    model, Zt = curves["model"], curves["Z"]
    dev = deviation(res, Zt, W_BAND if band_rad_s is None else band_rad_s)
    return {
        "model": model,
        "plant": {"m": plant.m, "b": plant.b},
        "ve": ve.as_dict(),
        "latency_s": latency,
        "Z_theory": Zt,
        "Z_paper": curves["paper"],
        "deviation": np.abs(res.Z - Zt) / np.abs(Zt),
        "deviation_median": dev["median_rel"],
        "deviation_max": dev["max_rel"],
        "deviation_max_rad_s": dev["max_rad_s"],
        "deviation_max_band_rel": dev["max_band_rel"],
        "band_rad_s": dev["band_rad_s"],
        "predicted_ws_star": linear.predicted_ws_star(plant, ve),
        "predicted_wb_star": linear.predicted_wb_star(ve),
    }
