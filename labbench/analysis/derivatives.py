"""Velocity and acceleration from sampled position by zero-phase filtered
differences (paper sec. 4.1: non-causal filtered differentiation).

The low-pass is a Butterworth filter run forward and backward
(``scipy.signal.sosfiltfilt``): zero phase, magnitude |H|^2, so with the
cut-off a few times above the excited band the passband error is far below
1e-3 and the derivatives are not delayed against the force.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, signal

ORDER = 4  # per pass; the forward-backward magnitude is that of order 8
# Cut-off = CUTOFF_FACTOR x the frequency holding 99.5 % of the force power:
# |H(f)|^2 at f = fc/3 is 1 - 1.5e-4, so the excited band passes unchanged.
CUTOFF_FACTOR = 3.0
FORCE_POWER_FRACTION = 0.995
# Cap of the default cut-off (fraction of fs): central differences are then within
# (2 pi 0.05)^2 / 6 = 1.6 % of a derivative at the cut-off, far less below it.
MAX_CUTOFF = 0.05


@dataclass(frozen=True)
class Derivatives:
    x: np.ndarray  # filtered position [m]
    v: np.ndarray  # velocity [m/s]
    a: np.ndarray  # acceleration [m/s^2]
    keep: slice  # samples kept after edge trimming (index into the input)
    v_all: np.ndarray  # velocity at every input sample (one-sided differences at the ends)
    cutoff_hz: float
    noise_gain: tuple[float, float]  # rms of v, a per unit white position noise


def force_band(force: np.ndarray, fs: float) -> float:
    """Frequency [Hz] below which FORCE_POWER_FRACTION of the force power lies.

    A 5-point running median first removes isolated spikes (sensor glitches),
    whose flat spectrum would otherwise widen the band.
    """
    f = ndimage.median_filter(np.asarray(force, float), size=5, mode="nearest")
    p = np.abs(np.fft.rfft(f - np.mean(f))) ** 2
    p[0] = 0.0
    c = np.cumsum(p)
    if c[-1] <= 0:
        return fs / 2
    return float(np.searchsorted(c, FORCE_POWER_FRACTION * c[-1]) * fs / len(f))


def default_cutoff(band_hz: float, fs: float) -> float:
    """Cut-off [Hz] from the data: CUTOFF_FACTOR x the band holding most force power
    (``force_band``).

    Clipped to [fs/2000, MAX_CUTOFF x fs]: a broadband (white) excitation gets
    a filter well below Nyquist, and the force is then filtered with it too.
    """
    return float(np.clip(CUTOFF_FACTOR * band_hz, fs / 2000, MAX_CUTOFF * fs))


def lowpass(values: np.ndarray, fs: float, cutoff_hz: float) -> np.ndarray:
    """The same zero-phase low-pass as the derivatives use (for matched filtering)."""
    return signal.sosfiltfilt(_lowpass(cutoff_hz, fs), np.asarray(values, float))


def _lowpass(cutoff_hz: float, fs: float):
    return signal.butter(ORDER, min(cutoff_hz, 0.45 * fs), fs=fs, output="sos")


# Difference stencils (offsets -2..2, to be divided by T and T^2), by how the force reached
# the plant (``labbench.analysis.identify``'s force_hold):
# * "zoh": a held force, whose sample pairs with the mean of the two held values around it,
#   i.e. the hat-weighted mean over [t - T, t + T] of the force; the model holds for the same
#   mean of x'' (exactly the 3-point second difference) and of x' (5 taps matching its
#   response j w (1 - (w T)^2 / 12) to fourth order; the 3-point central difference's
#   1 - (w T)^2 / 6 read b 2e-6 high on exact chirps);
# * "sample": a force read at the sampling instants: x' and x'' there, the 5-point
#   fourth-order differences (the 3-point second difference reads x'' high by (w T)^2 / 12,
#   0.13 % at 20 Hz and 1 kHz, a bias in m).
STENCILS = {
    "zoh": (np.array([1.0, -14.0, 0.0, 14.0, -1.0]) / 24, np.array([0.0, 1.0, -2.0, 1.0, 0.0])),
    "sample": (np.array([1.0, -8.0, 0.0, 8.0, -1.0]) / 12, np.array([-1.0, 16.0, -30.0, 16.0, -1.0]) / 12),
}


def differentiate(x: np.ndarray, fs: float, cutoff_hz: float, stencil: str = "zoh") -> Derivatives:
    """Filter x (zero phase), then the ``stencil``'s differences for x' and x''.

    Edges are trimmed by a few filter time constants (transients of the
    forward-backward pass) and two samples for the differences.
    """
    x = np.asarray(x, float)
    sos = _lowpass(cutoff_hz, fs)
    xf = signal.sosfiltfilt(sos, x)
    T = 1.0 / fs
    dv, da = STENCILS[stencil]
    v = _apply(xf, dv) / T
    a = _apply(xf, da) / T**2
    trim = 2 + int(np.ceil(3.0 * fs / cutoff_hz))
    trim = min(trim, (len(x) - 8) // 4)
    keep = slice(trim, len(x) - trim)
    v_all = np.gradient(xf, T)  # every sample (one-sided at the ends), for the velocity's sign
    return Derivatives(xf[keep], v[keep], a[keep], keep, v_all, float(cutoff_hz),
                       _noise_gain(sos, T, stencil))


def _apply(x: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """sum_j taps[j] x[k + j - 2] at every k with all five neighbours (the two at each end: 0)."""
    out = np.zeros_like(x)
    out[2:-2] = sum(c * x[j:len(x) - 4 + j] for j, c in enumerate(taps) if c)
    return out


def _noise_gain(sos, T: float, stencil: str) -> tuple[float, float]:
    """Rms of (v, a) per unit-variance white noise in position, from the impulse response."""
    n = 4096
    imp = np.zeros(n)
    imp[n // 2] = 1.0
    h = signal.sosfiltfilt(sos, imp)
    dv, da = STENCILS[stencil]
    return (float(np.sqrt(np.sum((_apply(h, dv) / T) ** 2))),
            float(np.sqrt(np.sum((_apply(h, da) / T**2) ** 2))))


def velocity_beyond(force: np.ndarray, fs: float, cutoff_hz: float, mass: float) -> float:
    """Rms [m/s] of the velocity the zero-phase low-pass at ``cutoff_hz`` leaves out of a
    mass ``mass`` [kg] driven by the held ``force`` [N]: beyond the excited band a device is
    its mass, whose sampled velocity is the held force's sum, |V / F| = T / (2 m sin(w T / 2))
    (-> 1 / (w m) below Nyquist), and the filtered velocity misses (1 - |H|^2) of it (|H|^2:
    the forward-backward magnitude), summed over the force's spectrum (Parseval). A white-noise
    excitation, whose power runs past the cut-off (capped at MAX_CUTOFF fs), leaves several
    mm/s there (0.5 N, 1 kHz, 50 Hz, 0.094 kg: 5.0 mm/s); a band-limited one next to none."""
    f = np.asarray(force, float)
    if not mass > 0 or len(f) < 2:
        return 0.0
    hz = np.fft.rfftfreq(len(f), 1.0 / fs)[1:]
    power = np.abs(np.fft.rfft(f)[1:]) ** 2 * 2.0 / len(f) ** 2  # one-sided: sum = variance
    if len(f) % 2 == 0:
        power[-1] /= 2.0
    _, h = signal.sosfreqz(_lowpass(cutoff_hz, fs), worN=hz, fs=fs)
    left = (1.0 - np.abs(h) ** 2) / (2.0 * mass * fs * np.sin(np.pi * hz / fs))
    return float(np.sqrt(np.sum(power * left**2)))
