"""When a lab's sketch really takes its samples, by how it schedules them on an AVR.

The driver puts every ASCII sample k at k T (``StreamDecoder``); these are the true
instants behind that, and ``etfe_errors`` measures what each costs (bench/bench_stamps.py,
tests/test_stamp_cost.py, docs/serial-protocol.md "What the time field costs"):

* ``micros_grid``: ``if ((long)(micros() - due) >= 0) { due += PERIOD; ... }`` - on the
  grid, late by the loop's polling (micros() counts in 4 us steps at 16 MHz).
* ``millis_grid``: the same on millis(). Timer0 overflows every 1.024 ms; each overflow
  adds 1 to millis() and 3 to a fraction that adds one more millisecond when it reaches
  125 (the core's wiring.c: MILLIS_INC 1, FRACT_INC 3, FRACT_MAX 125), so millis() after n
  overflows is n + floor(3 n / 125) and a sample is taken at the first overflow whose
  millis() reaches its due time: 9.216 or 10.24 ms apart around a 10 ms mean.
* ``delay_loop``: ``delay(PERIOD_MS)`` then read and print: every period is the delay
  plus the loop's own work (``work_s``: reading, formatting, queueing the line).
"""
from __future__ import annotations

import numpy as np

BAND = (2.0, 100.0)  # rad/s: the paper's band, where the errors are measured
WORK_S = 2e-4  # a delay() loop's own work per period: read, format, queue the line
OVERFLOW_S = 1.024e-3  # timer0 at 16 MHz / 64 / 256
POLL_S = 12e-6  # a loop() that does little else comes round this often


def micros_grid(n: int, T: float, rng: np.random.Generator) -> np.ndarray:
    """True instants [s] of n samples scheduled on micros()."""
    return np.arange(n) * T + np.floor(rng.uniform(0, POLL_S, n) / 4e-6) * 4e-6


def millis_of(overflows: np.ndarray) -> np.ndarray:
    """millis() after ``overflows`` timer0 overflows (Arduino AVR core)."""
    return overflows + (3 * overflows) // 125


def millis_grid(n: int, T: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(true instants [s], printed millis()) of n samples scheduled on millis() every T."""
    period_ms = round(T * 1e3)
    due = np.arange(n) * period_ms
    # the first overflow whose millis() reaches each due time
    upper = int(n * period_ms / 1.024) + 4
    overflows = np.arange(upper)
    first = np.searchsorted(millis_of(overflows), due, side="left")
    t = first * OVERFLOW_S + rng.uniform(0, POLL_S, n)
    return t, millis_of(first)


def delay_loop(n: int, T: float, work_s: float, rng: np.random.Generator) -> np.ndarray:
    """True instants [s] of n samples taken by a loop of ``delay(T)`` and ``work_s`` of work
    (varying by +-10 %)."""
    steps = T + work_s * rng.uniform(0.9, 1.1, n)
    return np.r_[0.0, np.cumsum(steps[:-1])]


def positions_at(instants: np.ndarray, force: np.ndarray, m: float, b: float) -> np.ndarray:
    """Positions [m] at ``instants`` of a mass-damper at rest at 0 at the first, driven by
    ``force[k]`` held from ``instants[k]`` to ``instants[k + 1]`` (the host answers each
    sample; the board's own timing is the hold), integrated exactly between them
    (``labbench.model.linear.zoh_matrices``)."""
    from labbench.model.linear import zoh_matrices

    cache: dict = {}
    state = np.zeros(2)
    out = np.empty(len(instants))
    steps = np.diff(instants)
    for k in range(len(instants)):
        out[k] = state[0]
        if k < len(steps):
            dt = round(float(steps[k]), 9)
            if dt not in cache:
                cache[dt] = zoh_matrices(m, b, dt)
            A, B = cache[dt]
            state = A @ state + B * force[k]
    return out


def sampled_Z(w: np.ndarray, m: float, b: float, hold: float, T: float) -> np.ndarray:
    """F / (j w X) of the exact sampled mass-damper whose force is held ``hold`` seconds a
    sample, read as samples T apart (``hold`` = T: the exact sampled model)."""
    from labbench.model.linear import zoh_matrices

    Ad, Bd = zoh_matrices(m, b, hold)
    z = np.exp(1j * w * T)
    G = np.array([np.linalg.solve(zz * np.eye(2) - Ad, Bd)[0] for zz in z])
    return 1.0 / (1j * w * G)


def etfe_errors(T: float, seconds: float, seed: int = 1) -> dict:
    """Per regime: median and max relative error of the ETFE against the sampled model
    (and, for the delay loop, against its prediction)."""
    from labbench.analysis.dataio import recording_from_arrays
    from labbench.analysis.etfe import etfe
    from labbench.rig import Rig

    rig = Rig()
    m, b, mpc = rig.nominal_mass_kg, rig.nominal_damping_ns_m, rig.metres_per_count
    n = int(round(seconds / T))
    rng = np.random.default_rng(seed)
    force = rng.normal(0.0, 0.5, n)
    regimes = {"micros grid": micros_grid(n, T, rng),
               "millis grid": millis_grid(n, T, rng)[0],
               "delay loop, no time": delay_loop(n, T, WORK_S, rng)}
    out = {}
    for name, instants in regimes.items():
        x = positions_at(instants, force, m, b)
        x = np.floor(x / mpc + 0.5) * mpc  # the encoder's counts
        est = etfe(recording_from_arrays(np.arange(n) * T, force, x), band_rad_s=BAND)
        w, Z = np.asarray(est.w), np.asarray(est.Z)
        sel = (w >= BAND[0]) & (w <= BAND[1])
        w, Z = w[sel], Z[sel]
        rel = np.abs(Z - sampled_Z(w, m, b, T, T)) / np.abs(sampled_Z(w, m, b, T, T))
        row = {"median": float(np.median(rel)), "max": float(rel.max())}
        if name.startswith("delay"):
            pred = sampled_Z(w, m, b, T + WORK_S, T)
            row["vs_predicted"] = float(np.median(np.abs(Z - pred) / np.abs(pred)))
            row["predicted_median"] = float(np.median(np.abs(pred - sampled_Z(w, m, b, T, T))
                                                      / np.abs(sampled_Z(w, m, b, T, T))))
        out[name] = row
    return out
