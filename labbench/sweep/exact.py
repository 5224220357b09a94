"""Records with known truth: what an analysis sweep (and the analysis tests) feed the estimators.

Open loop (identification): ``open_loop`` integrates m x'' + b x' + Fc sign(x') = f
with f held constant over each sample (zero-order hold) *piecewise
analytically*: between events the motion is the exact solution of a linear ODE
with constant input; a velocity zero crossing inside a step is located from the
closed-form v(t) and the step continues (or sticks, if |f| <= Fc) from there.
So the samples are exact up to floating point: no integrator error to mistake
for estimator error.

Closed loop (ETFE): ``closed_loop_recording`` runs the exact sampled loop of
``labbench.model.linear.closed_loop`` (input f_exo[k], output x[k]) through
``scipy.signal.dlsim``; its frequency response ``z_truth`` is the truth.

Measurement errors are added to the recorded channels only (``with_noise``,
``measured``): the loop that made the record saw the exact position. That
isolates what an estimator does with imperfect data; the simulator
(``labbench sweep`` kind "run") is where quantisation and noise act inside the loop.
"""
from __future__ import annotations

import math

import numpy as np

from labbench.analysis.dataio import Recording, recording_from_arrays

PAPER_M, PAPER_B = 0.094, 0.10


def chirp_force(n: int, fs: float = 1000.0, f0: float = 0.1, f1: float = 20.0, amp: float = 1.0):
    """Linear chirp f0 -> f1 Hz over n samples, amplitude amp [N]."""
    t = np.arange(n) / fs
    dur = n / fs
    return amp * np.sin(2 * np.pi * (f0 * t + (f1 - f0) / (2 * dur) * t**2))


def open_loop(force, m: float, b: float, fs: float = 1000.0, coulomb: float = 0.0,
              offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Exact samples x[k], v[k] of m x'' + b x' + Fc sign(x') + f0 = f (ZOH force; b > 0).

    ``offset`` f0 is a constant force the sensor does not see (e.g. gravity, cable).
    """
    T = 1.0 / fs
    a = b / m
    x = np.empty(len(force))
    v_out = np.empty(len(force))
    pos, vel = 0.0, 0.0
    for k, f in enumerate(np.asarray(force, float)):
        x[k], v_out[k] = pos, vel
        tau = T
        while tau > 0:
            if vel == 0.0 and abs(f - offset) <= coulomb:
                break  # stuck for the rest of the step
            direction = np.sign(vel) if vel != 0.0 else np.sign(f - offset)
            u = f - offset - coulomb * direction
            vinf = u / b
            # time at which v reaches 0 (if it does, while moving against u)
            t0 = math.inf
            if vel != 0.0 and np.sign(vinf) != np.sign(vel):
                t0 = math.log((vinf - vel) / vinf) / a
            step = min(tau, t0)
            e = math.exp(-a * step)
            pos = pos + vinf * step + (vel - vinf) * (1 - e) / a
            vel = 0.0 if step == t0 else vinf + (vel - vinf) * e
            tau -= step
    return x, v_out


def chirp_recording(n: int = 60000, m: float = PAPER_M, b: float = PAPER_B, fs: float = 1000.0,
                    coulomb: float = 0.0, offset: float = 0.0, amp: float = 1.0,
                    f1: float = 20.0) -> Recording:
    f = chirp_force(n, fs, f1=f1, amp=amp) + offset
    x, _ = open_loop(f, m, b, fs, coulomb, offset)
    return recording_from_arrays(np.arange(n) / fs, f, x, {"fs": fs}, "<chirp truth>")


def with_noise(rec: Recording, rng, force_noise: float = 0.0, quantum: float = 0.0,
               outlier_fraction: float = 0.0, outlier_size: float = 0.0) -> Recording:
    """Copy with white force noise [N rms], position quantisation [m], sparse force spikes."""
    f = rec.force + force_noise * rng.standard_normal(len(rec.force))
    if outlier_fraction:
        idx = rng.choice(len(f), int(outlier_fraction * len(f)), replace=False)
        f[idx] += outlier_size * rng.choice([-1.0, 1.0], len(idx))
    x = np.round(rec.position / quantum) * quantum if quantum else rec.position.copy()
    return recording_from_arrays(rec.t, f, x, rec.meta, rec.source + " (noisy)")


def measured(rec: Recording, rng, quantum: float = 0.0, position_noise: float = 0.0,
             force_noise_rel: float = 0.0) -> Recording:
    """Copy as a sensor would read it: white position noise [m rms], then quantisation to
    ``quantum`` [m]; white force noise of ``force_noise_rel`` x the force's std. Both noises
    are drawn (position first) whatever their size, so one seed gives one pair of streams."""
    x = rec.position + position_noise * rng.standard_normal(len(rec.t))
    if quantum:
        x = np.round(x / quantum) * quantum
    f = rec.force + force_noise_rel * np.std(rec.force) * rng.standard_normal(len(rec.t))
    return recording_from_arrays(rec.t, f, x, rec.meta)


def closed_loop_recording(ve, n: int = 120000, m: float = PAPER_M, b: float = PAPER_B,
                          seed: int = 0, force_std: float = 1.0, latency: float = 0.0,
                          process_noise: float = 0.0) -> Recording:
    """White-noise exogenous force through the exact sampled loop (linear.closed_loop; ``latency``
    [s]: the rig's actuator delay, not in the metadata; ``process_noise`` [N rms]: white force
    the plant feels but the record does not hold, like the simulator's force_noise_n)."""
    from scipy import signal

    from labbench.model import linear
    from labbench.model.ve import Plant

    rng = np.random.default_rng(seed)
    f = force_std * rng.standard_normal(n)
    loop = linear.closed_loop(Plant(m, b), ve, latency)
    _, y, _ = signal.dlsim(loop.as_dlti(), f + process_noise * rng.standard_normal(n))
    meta = {"fs": 1.0 / ve.T, **{k: v for k, v in ve.as_dict().items() if k != "T" and v is not None}}
    meta["ve"] = meta.pop("kind")
    return recording_from_arrays(np.arange(n) * ve.T, f, y[:, 0], meta, "<closed-loop truth>")


def z_truth(ve, w, m: float = PAPER_M, b: float = PAPER_B, latency: float = 0.0) -> np.ndarray:
    """Exact sampled impedance at w: what an ETFE of closed_loop_recording converges to."""
    from labbench.model import linear
    from labbench.model.ve import Plant

    return linear.z_sampled(Plant(m, b), ve, w, latency)
