"""Data with known truth for the analysis tests and the benchmark.

The exact open-loop and closed-loop records live in ``labbench.sweep.exact`` (an
analysis sweep feeds them to the estimators); this module adds the test-only ones.
"""
from __future__ import annotations

import math

import numpy as np

from labbench.analysis.dataio import Recording, recording_from_arrays
from labbench.sweep.exact import (  # noqa: F401 - the tests' names for them
    PAPER_B,
    PAPER_M,
    chirp_force,
    chirp_recording,
    closed_loop_recording,
    open_loop,
    with_noise,
    z_truth,
)


def sensor_chirp_recording(n: int = 30000, m: float = PAPER_M, b: float = PAPER_B, fs: float = 1000.0,
                           amp: float = 1.0, f1: float = 20.0, oversample: int = 16) -> Recording:
    """A continuous chirp force (as a force sensor reads it) on m x'' + b x' = f, sampled.

    The force is the chirp at every instant, not held: ``scipy.signal.lsim`` integrates
    the linear ODE exactly for a piecewise-linear input on a grid ``oversample`` times
    finer than the samples (the chirp's curvature between grid points is ~1e-7 of it).
    The record is meant to be read with ``force_hold = sample``.
    """
    from scipy import signal

    t = np.arange(n * oversample) / (fs * oversample)
    f = chirp_force(n * oversample, fs * oversample, f1=f1, amp=amp)
    plant = signal.lti([[0.0, 1.0], [0.0, -b / m]], [[0.0], [1.0 / m]], [[1.0, 0.0]], [[0.0]])
    _, x, _ = signal.lsim(plant, f, t)
    return recording_from_arrays(t[::oversample], f[::oversample], x[::oversample], {"fs": fs},
                                 "<sensor chirp truth>")


def write_csv(rec: Recording, path, extra_meta: dict | None = None) -> None:
    """CSV in the documented layout (# key=value lines, header, rows), columns shuffled."""
    with open(path, "w") as fh:
        fh.writelines(f"# {k}={v}\n" for k, v in {**rec.meta, **(extra_meta or {})}.items())
        fh.write("position,t,force\n")
        np.savetxt(fh, np.column_stack([rec.position, rec.t, rec.force]), delimiter=",", fmt="%.17g")


def delayed_loop_recording(ve, n: int = 30000, m: float = PAPER_M, b: float = PAPER_B,
                           latency: float = 0.0, ve_delay: float = 0.0, seed: int = 0,
                           force_std: float = 1.0, force_noise: float = 0.0,
                           process_noise: float = 0.0) -> Recording:
    """A closed-loop white-noise record simulated step by step in the time domain, with the
    excitation reaching the plant ``latency`` [s] after its sample and the VE force
    ``latency + ve_delay`` after its own (either a fraction of a sample or not).

    Brute force, independent of ``labbench.model.linear``: each step is cut where either held
    input changes, and every piece integrated exactly (``scipy.linalg.expm`` of the
    augmented plant). The VE is ``ve``'s law (K, B, w0 filter) with its td ignored: the
    metadata say td = 0, so the VE-path delay is undeclared. ``force_noise`` [N rms] is
    added to the recorded force only (a force sensor's noise; the metadata then leave
    force_hold unsaid), ``process_noise`` [N rms] to the force the plant feels only (the
    recorded force is then the command: force_hold = zoh).
    """
    from scipy.linalg import expm

    T = ve.T
    rng = np.random.default_rng(seed)
    f_exo = force_std * rng.standard_normal(n)
    felt = f_exo + process_noise * rng.standard_normal(n) if process_noise else f_exo
    cuts = sorted({0.0, T, *(((d / T) % 1.0) * T for d in (latency, latency + ve_delay))})
    pieces = []  # (Phi, Gamma, exo index offset, VE index offset) per piece of a step
    A = np.array([[0.0, 1.0], [0.0, -b / m]])
    for t0, t1 in zip(cuts[:-1], cuts[1:]):
        if t1 - t0 < 1e-15:
            continue
        aug = np.zeros((3, 3))
        aug[:2, :2], aug[1, 2] = A * (t1 - t0), (t1 - t0) / m
        E = expm(aug)
        mid = 0.5 * (t0 + t1)
        pieces.append((E[:2, :2], E[:2, 2], math.floor((mid - latency) / T),
                       math.floor((mid - latency - ve_delay) / T)))
    a = math.exp(-ve.w0 * T) if math.isfinite(ve.w0) else 0.0
    state = np.zeros(2)
    x = np.empty(n)
    f_ve = np.zeros(n)
    v_hat, x_prev = 0.0, 0.0
    for k in range(n):
        x[k] = state[0]
        v_hat = a * v_hat + (1 - a) * (x[k] - x_prev) / T
        x_prev = x[k]
        f_ve[k] = (ve.K * x[k] + ve.B * v_hat) if ve.kind != "none" else 0.0
        for Phi, G, oe, ov in pieces:
            u = (felt[k + oe] if k + oe >= 0 else 0.0) - (f_ve[k + ov] if k + ov >= 0 else 0.0)
            state = Phi @ state + G * u
    meta = {"fs": 1.0 / T, "ve": ve.kind, "K": ve.K, "B": ve.B,
            "w0": ve.w0 if math.isfinite(ve.w0) else "none", "td": 0.0}
    if not force_noise:
        meta["force_hold"] = "zoh"
    recorded = f_exo + force_noise * rng.standard_normal(n)
    return recording_from_arrays(np.arange(n) * T, recorded, x, meta, "<delayed-loop truth>")


def off_the_half_way_level(wb: float, plant, ve) -> float:
    """How far the exact sampled ED at a measured w_b* ``wb`` [rad/s] lies from the half-way
    level that defines w_b* (``labbench.model.effective.measured_wb_star``), as a share of ED's fall
    from ED(0) to the device b: 0 at the truth's w_b*, 0.5 at the top or the foot of the fall."""
    from labbench.model import linear

    ed0 = float(np.median(linear.z_sampled(plant, ve, np.geomspace(1e-3, 2e-3, 3)).real))
    ed = float(linear.z_sampled(plant, ve, [wb]).real[0])
    return abs(ed - (plant.b + 0.5 * (ed0 - plant.b))) / (ed0 - plant.b)
