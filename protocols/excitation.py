"""Exogenous force signals for the protocols: chirps, white noise, a probe pulse.

All functions return one force value per sample period T [s], in newtons.
"""
from __future__ import annotations

import math

import numpy as np

SWEEPS = ("log", "linear")


def chirp_phase(n: int, T: float, f0_hz: float, f1_hz: float, sweep: str = "log"):
    """Phase [rad] and instantaneous frequency [Hz] of a chirp sweeping f0 -> f1 over n*T.

    Logarithmic sweep: f(t) = f0 r^(t/D), r = f1/f0, phase 2 pi f0 D (r^(t/D) - 1) / ln r;
    linear sweep: f(t) = f0 + (f1 - f0) t / D (the usual closed forms of the phase integral).
    """
    if sweep not in SWEEPS:
        raise ValueError(f"sweep must be one of {SWEEPS}")
    t = np.arange(n) * T
    D = n * T
    if sweep == "log" and f1_hz != f0_hz:
        r = f1_hz / f0_hz
        f = f0_hz * r ** (t / D)
        phase = 2 * np.pi * f0_hz * D * (r ** (t / D) - 1.0) / math.log(r)
    else:
        f = f0_hz + (f1_hz - f0_hz) * t / D
        phase = 2 * np.pi * (f0_hz * t + 0.5 * (f1_hz - f0_hz) * t**2 / D)
    return phase, f


def displacement_envelope(f_hz: np.ndarray, m: float, b: float, x_max_m: float, amplitude_n: float):
    """Force amplitude per instantaneous frequency that keeps the free mass-damper's
    steady-state displacement at most ``x_max_m``: A(f) = min(amplitude, x_max w |b + j w m|)
    (|X/F| = 1 / (w |b + j w m|) for m x'' + b x' = f)."""
    w = 2 * np.pi * np.asarray(f_hz, float)
    return np.minimum(amplitude_n, x_max_m * w * np.abs(b + 1j * w * m))


def fade(n: int, n_fade: int) -> np.ndarray:
    """Raised-cosine fade-in and fade-out of ``n_fade`` samples each (ones in between)."""
    g = np.ones(n)
    n_fade = min(n_fade, n // 2)
    if n_fade > 0:
        ramp = 0.5 - 0.5 * np.cos(np.pi * (np.arange(n_fade) + 0.5) / n_fade)
        g[:n_fade] = ramp
        g[n - n_fade:] = ramp[::-1]
    return g


def chirp(n: int, T: float, f0_hz: float, f1_hz: float, envelope, sweep: str = "log",
          n_fade: int = 0) -> np.ndarray:
    """Chirp force ``envelope(f) * sin(phase)`` with a raised-cosine fade at both ends.

    ``envelope`` is a number (constant amplitude, N) or a callable of the
    instantaneous frequency [Hz] returning the amplitude [N].
    """
    phase, f = chirp_phase(n, T, f0_hz, f1_hz, sweep)
    amp = envelope(f) if callable(envelope) else np.full(n, float(envelope))
    return amp * np.sin(phase) * fade(n, n_fade)


def white_noise(n: int, T: float, std_n: float, band_hz: tuple[float, float] | None = None,
                seed: int | None = None) -> np.ndarray:
    """Gaussian white force, optionally band-limited to ``band_hz`` = (low, high) Hz.

    Band limiting is done by zeroing FFT bins outside the band (zero phase, exact
    edges), then the signal is rescaled to the requested standard deviation.
    """
    rng = np.random.default_rng(seed)
    u = rng.standard_normal(n)
    if band_hz is not None:
        lo, hi = band_hz
        U = np.fft.rfft(u)
        f = np.fft.rfftfreq(n, T)
        U[(f < lo) | (f > hi)] = 0.0
        U[0] = 0.0
        u = np.fft.irfft(U, n)
    u = u - u.mean()
    s = u.std()
    return u * (std_n / s) if s > 0 else u


def pulse(n: int, T: float, amplitude_n: float, width_s: float, at_s: float = 0.0) -> np.ndarray:
    """One half-sine force pulse of peak ``amplitude_n`` and length ``width_s`` starting at ``at_s``."""
    out = np.zeros(n)
    k0 = round(at_s / T)
    w = max(1, round(width_s / T))
    k1 = min(n, k0 + w)
    out[k0:k1] = amplitude_n * np.sin(np.pi * (np.arange(k1 - k0) + 0.5) / w)
    return out
