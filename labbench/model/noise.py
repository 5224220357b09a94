"""The force noise a haptic loop commands: the encoder step and the amplifier's noise pushed
through the exact sampled closed loop.

**Sources.** The loop computes its VE force from the position the encoder reports, in whole
steps of Delta [m] at the handle (``Rig.metres_per_count``): x_q = x + e. Where the motion
spans many steps between samples, e is white, uniform on [-Delta/2, Delta/2), of variance
Delta^2 / 12 and uncorrelated with x (Bennett, "Spectra of quantized signals", Bell Syst.
Tech. J. 27, 1948; Widrow & Kollar, *Quantization Noise*, Cambridge 2008, chs. 4-5 and 11).
The rig may state an amplifier (or actuator) noise too: white force noise n_f of std
``force_noise_n`` [N] added to the applied force, held over each step (the simulator's
``[sim] force_noise_n``; a drive's torque set point in whole units of 1/1000 of its rated
torque adds its own step q_F the same way, std q_F / sqrt(12)).

**When e is white** (derived here from the Fourier series of the rounding error, the route of
Widrow & Kollar ch. 11): e(x) = x - Delta round(x / Delta) is a sawtooth of period Delta,
sum_n (-1)^(n+1) Delta / (pi n) sin(2 pi n x / Delta). For a motion whose position spreads
over many steps (std >> Delta: the first condition, Widrow's quantising theorem nearly met)
and whose increment d_j = x[k+j] - x[k] is Gaussian with variance D_j, the correlation of
e[k] and e[k+j] is

    rho_j = (6 / pi^2) sum_{n >= 1} exp(-2 pi^2 n^2 D_j / Delta^2) / n^2

(1 at D_j = 0; 6 / pi^2 exp(-2 pi^2 D_j / Delta^2) once D_j is a fair share of Delta^2).
The second condition, whiteness, is rho_1 small: below 1 % once the position moves at least
0.456 Delta rms from one sample to the next (``white_speed``: 17.5 mm/s for the default
rig's 38.3 um at 1 kHz). Slower motion makes e a slow sawtooth: the same power, shifted to
low frequencies. Given the motion's increments (``increments``: from a white excitation
through this same loop, or a hand's rms speed) the model uses the rho_j spectrum instead of
the white one; a handle at rest commands no quantisation noise at all.

**Through the loop** (``labbench.model.linear``, exact sampled, with the device's latency):
with P the held plant, G = z^-n C the VE's path from sampled position to command and
L = G P, the loop x = P (u + n_f), u = f_exo - G (x + e) gives

    u_noise = -G / (1 + L) e  -  L / (1 + L) n_f          (the command the loop records)
    f_noise = -G / (1 + L) e  +  1 / (1 + L) n_f          (the force at the actuator, u + n_f)

Their one-sided spectra [N^2/Hz] are |H|^2 S; the RMS is the root of their integral over a
band. The force a hand feels is held over each step: its spectrum at a frequency f is the
sampled one at f folded into [0, 1 / (2T)] times sinc^2(f T), the hold's images included
(Franklin, Powell & Workman sec. 4.2), so a slower loop both concentrates the noise and
puts images of it above its Nyquist frequency.

**The band a person feels.** Colonnese et al. sec. 5: humans detect haptic signals up to
500 Hz (their ref. 6, Hale & Stanney, IEEE CG&A 24(2), 2004), while volitional movement
stays below 10 Hz (their ref. 9, Lawrence et al. 1996). Force below 10 Hz is felt as the
environment the hand moves in; above it, up to 500 Hz, as vibration: ``FELT_BAND_HZ``.

**Coulomb friction** Fc sign(v) (``NoiseSources.coulomb_n``, under a stated excitation:
``Excitation``) is split by statistical linearisation into the damper it acts as and a
remnant uncorrelated with the velocity,

    Fc sign(v) = b_eq v + d,      b_eq = Fc sqrt(2/pi) / sigma_v

(Booton, IRE Trans. Circuit Theory 1(1), 1954; ``labbench.model.friction``): the loop is
the linear one with b + b_eq, and d is one more force noise entering with the command (as
n_f does: -L/(1 + L) d in the command). For a Gaussian excitation the ETFE's response is
that loop (Bussgang: the best linear approximation), and d is the nonlinear distortion that
no linear response to the excitation explains, which a record's noise estimate takes as noise
(Pintelon & Schoukens, *System Identification*, 2nd ed. 2012, sec. 3.4: nonlinear distortion
as a noise source). For a Gaussian velocity of correlation rho(tau) the sign's correlation is
the arcsine law, E[sign v(t) sign v(t + tau)] = (2/pi) arcsin rho(tau) (Van Vleck &
Middleton, Proc. IEEE 54(1), 1966), so d's correlation is

    R_d(tau) = Fc^2 (2/pi) (arcsin rho(tau) - rho(tau))

(the cross term is b_eq^2 R_v, Bussgang's theorem), and its spectrum one FFT of it
(``sign_remnant``). rho is the velocity's at the sample instants of the linearised loop,
driven by the excitation, the amplifier's noise, the quantisation error (white) and d
itself; b_eq, sigma_v and d are solved together (Brent's method on b_eq sigma_v(b + b_eq) =
Fc sqrt(2/pi), as ``labbench.model.friction.linearise`` does, d's own share of the velocity
found by fixed point inside it). The friction a record shows acts continuously; the model
takes its remnant at the sample instants, held over each step: a record's d reverses
seldom within a step at the speeds where the rest holds.

**Where it holds.** A Gaussian velocity is the assumption. At a reversal the handle sticks
when the applied force is within +-Fc; by Rice's density of the slope at a zero crossing
(Rice, "Mathematical analysis of random noise", Bell Syst. Tech. J. 23, 1944, sec. 3.3:
a crossing's slope is weighted by its size) the share of reversals that stick is

    p_stick = 1 - exp(-Fc^2 / (2 sigma_u^2)),

sigma_u the applied force's rms in the linearised loop (``FrictionPart.stick_share``).
Measured on the rough simulator, p_stick follows the share of time the handle is at rest
(0.5 / 2.0 / 3.1 % predicted, 0.2-0.3 / 1.6-1.8 / 3.0-3.3 % measured) and the model holds
the command noise within 10 % where p_stick <= ``STICK_SHARE_MAX`` (docs/design.md);
beyond it ``FrictionPart.gaussian`` is False and the numbers are a rough guess.
Where friction holds the handle (Fc sqrt(2/pi) at or above the rms of the forces that drive
it, excitation and amplifier: no damper stands for it, as in ``labbench.model.friction``;
d's own share does not count, or the remnant would drive the motion that makes it) there is
no prediction (UserError).

The handle is free (no hand in the loop); the felt force is the actuator's, friction's own
force at the handle not counted.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from scipy import optimize

from labbench.errors import UserError
from labbench.model import friction, linear
from labbench.model.ve import Plant, VirtualEnvironment

FELT_BAND_HZ = (10.0, 500.0)  # Colonnese et al. sec. 5 (module doc)
WHITE_RHO = 0.01  # lag-1 correlation of the quantisation error below which it counts as white
_SERIES = np.arange(1, 4097, dtype=float)  # terms of rho_j's series: error < 6 / (pi^2 4096)
_LAGS = 256  # lags of the coloured error spectrum (rho has decayed long before)
_MAX_POINTS = 1 << 21
STICK_SHARE_MAX = 0.01  # share of reversals that stick up to which friction's part holds (module doc)
_SEARCH_POINTS = 1 << 9  # least grid of the b_eq search (its integrals need only the poles' 10 / delta)
_REMNANT_TOL = 1e-4  # relative change of sigma_v at which d's share of the velocity has settled


@dataclass(frozen=True)
class NoiseSources:
    """What makes the noise: the encoder step ``quantum_m`` [m at the handle] (0: an ideal
    encoder), the std ``force_noise_n`` [N] of white force noise added to the applied
    force (the amplifier's; 0 when the rig states none) and the device's Coulomb friction
    ``coulomb_n`` [N] (0: none, or not known)."""

    quantum_m: float = 0.0
    force_noise_n: float = 0.0
    coulomb_n: float = 0.0

    def __post_init__(self):
        for name in ("quantum_m", "force_noise_n", "coulomb_n"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise UserError(f"{name} must be a finite number >= 0, got {v!r}")


@dataclass(frozen=True)
class Excitation:
    """The motion the noise is predicted under: white force of std ``std_n`` [N] added to the
    command (an ETFE's excitation), flat over ``band_hz`` (None: 0 to the Nyquist frequency;
    ``std_n`` is the std of the band-limited force, as ``protocols.excitation`` makes it)."""

    std_n: float
    band_hz: tuple[float, float] | None = None

    def __post_init__(self):
        if not (isinstance(self.std_n, (int, float)) and math.isfinite(self.std_n)
                and self.std_n > 0):
            raise UserError(f"excitation std must be a positive number of N, got {self.std_n!r}")
        if self.band_hz is not None and not (0 <= self.band_hz[0] < self.band_hz[1]):
            raise UserError(f"excitation band must be 0 <= low < high Hz, got {self.band_hz!r}")

    def psd(self, f: np.ndarray, T: float) -> np.ndarray:
        """One-sided spectrum [N^2/Hz] on the grid ``f`` (up to 1 / (2T))."""
        if self.band_hz is None:
            return np.full_like(f, 2 * T * self.std_n**2)
        lo, hi = self.band_hz[0], min(self.band_hz[1], 0.5 / T)
        return np.where((f >= lo) & (f <= hi), self.std_n**2 / (hi - lo), 0.0)


@dataclass(frozen=True)
class FrictionPart:
    """Coulomb friction ``coulomb_n`` [N] in the noise model (module doc): the damper
    ``b_eq`` [N s/m] it acts as at the velocity of rms ``velocity_rms`` [m/s] it leaves under
    white excitation of std ``excitation_n`` [N]; ``applied_rms`` [N] the applied force's rms;
    ``stick_share`` the share of reversals at which the handle sticks; ``gaussian``: that share
    within ``STICK_SHARE_MAX`` (where the model was measured to hold)."""

    coulomb_n: float
    b_eq: float
    velocity_rms: float
    applied_rms: float
    stick_share: float
    excitation_n: float

    @property
    def gaussian(self) -> bool:
        return self.stick_share <= STICK_SHARE_MAX

    def as_dict(self) -> dict:
        return {"coulomb_n": self.coulomb_n, "b_eq": self.b_eq, "velocity_rms": self.velocity_rms,
                "applied_rms": self.applied_rms, "stick_share": self.stick_share,
                "gaussian": self.gaussian, "excitation_n": self.excitation_n}


@dataclass(frozen=True)
class ForceNoise:
    """The predicted force noise of one loop (module doc).

    ``f_hz``: the frequency grid [0, 1/(2T)] (``frequency_grid``); ``psd_command`` / ``psd_force``: one-sided
    spectra [N^2/Hz] of the recorded command's noise and of the force at the actuator;
    ``rms_command``: the command's in ``band_hz`` (capped at the Nyquist frequency: a
    sampled record has nothing above it); ``rms_felt``: the held force at the actuator in
    ``band_hz`` (images of the hold included); ``rms_command_total``: over the whole
    Nyquist band; ``parts``: each source's share of ``rms_felt`` (root of its part of the
    power); ``white``: whether the quantisation error was taken as white, ``rho1`` its
    lag-1 correlation for the stated motion (None when no motion was stated), ``model``:
    which model said so; ``friction``: Coulomb friction's part (None without friction).
    """

    f_hz: np.ndarray
    psd_command: np.ndarray
    psd_force: np.ndarray
    band_hz: tuple[float, float]
    rms_command: float
    rms_felt: float
    rms_command_total: float
    parts: dict = field(default_factory=dict)
    white: bool = True
    rho1: float | None = None
    model: str = ""
    friction: FrictionPart | None = None

    def as_dict(self, spectrum: bool = False) -> dict:
        out = {"band_hz": list(self.band_hz), "rms_command_n": self.rms_command,
               "rms_felt_n": self.rms_felt, "rms_command_total_n": self.rms_command_total,
               "parts_n": dict(self.parts), "white": self.white, "rho1": self.rho1,
               "model": self.model,
               "friction": None if self.friction is None else self.friction.as_dict()}
        if spectrum:
            out.update(f_hz=self.f_hz.tolist(), psd_command=self.psd_command.tolist(),
                       psd_force=self.psd_force.tolist())
        return out


def error_correlation(increment_var, quantum: float) -> np.ndarray:
    """rho_j of the quantisation error for Gaussian increments of variance ``increment_var``
    [m^2] (module doc; 1 at 0, -> 0 as the increments grow past the step)."""
    D = np.atleast_1d(np.asarray(increment_var, float))
    if quantum <= 0:
        return np.zeros_like(D)
    a = 2 * math.pi**2 * D[:, None] / quantum**2
    # the terms past n fall below e^(-a n^2): a motion of a fair share of a step needs few
    least = float(a.min()) if a.size else 0.0
    n = len(_SERIES) if least <= 0 else min(len(_SERIES), math.ceil(math.sqrt(40.0 / least)) + 1)
    series = _SERIES[None, :n]
    terms = np.exp(-a * series**2) / series**2
    return (6 / math.pi**2) * terms.sum(axis=1)


def white_speed(quantum: float, T: float) -> float:
    """The rms speed [m/s] above which the error's lag-1 correlation is below ``WHITE_RHO``
    for motion at that speed (increment variance (v T)^2): the white model's condition."""
    if quantum <= 0:
        return 0.0
    lo, hi = 0.0, 2.0 * quantum  # rho_1 falls with the increment's std
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if error_correlation(mid**2, quantum)[0] > WHITE_RHO else (lo, mid)
    return hi / T


def increments_from_speed(speed_rms_m_s: float, T: float, lags: int = _LAGS) -> np.ndarray:
    """D_j = (v j T)^2, j = 1..lags: a hand moving at rms speed v, steady over a few samples."""
    j = np.arange(1, lags + 1)
    return (speed_rms_m_s * j * T) ** 2


def increments_from_excitation(plant: Plant, ve: VirtualEnvironment, std_n: float,
                               latency: float = 0.0, lags: int = _LAGS,
                               band_hz: tuple[float, float] | None = None) -> np.ndarray:
    """D_j = var(x[k+j] - x[k]), j = 1..lags, of the loop driven by white force of std
    ``std_n`` [N] (an ETFE's excitation; flat over ``band_hz``, None: the Nyquist band): the
    integral of |P / (1 + L)|^2 S_F (2 - 2 cos(2 pi f j T)) over the Nyquist band, each
    lag's cosine from one FFT."""
    f = _off_zero(frequency_grid(plant, ve, latency))
    P, G = linear.loop_parts(plant, ve, 2 * math.pi * f, latency)
    Sx = np.abs(P / (1 + G * P)) ** 2 * Excitation(std_n, band_hz).psd(f, ve.T)
    weights = _trapezoid_weights(f)
    # at f -> 0 the integrand tends to Sx (2 pi f j T)^2 (finite even where Sx is not: a
    # damper's position wanders), j^2 times this:
    at_zero = weights[0] * Sx[0] * (2 * math.pi * f[0] * ve.T) ** 2
    power = weights * Sx
    power[0] = 0.0
    cos_sums = _cosine_sums(power)[1:lags + 1]
    j = np.arange(1, lags + 1)
    return 2 * (np.sum(power) - cos_sums) + at_zero * j**2


def _cosine_sums(a: np.ndarray) -> np.ndarray:
    """sum_i a_i cos(pi i j / M), j = 0..M, of the M + 1 values ``a`` (on the grid f_i =
    i / (2 M T): the cosine series at lag j T), one real DFT of length 2M."""
    return np.fft.rfft(a, n=2 * (len(a) - 1)).real


def sign_remnant(f: np.ndarray, Sv: np.ndarray, coulomb_n: float, T: float
                 ) -> tuple[np.ndarray, float]:
    """(S_d, sigma_v): the one-sided spectrum [N^2/Hz] on the grid ``f`` (``frequency_grid``)
    of d = Fc sign(v) - b_eq v, b_eq = Fc sqrt(2/pi) / sigma_v, for a Gaussian velocity
    sampled every ``T`` of one-sided spectrum ``Sv`` [(m/s)^2/Hz] (the arcsine law, module
    doc); sigma_v its rms. R_v[j] is the cosine series of Sv (trapezoid rule); S_d that of
    R_d (R_d[j] for j > M wraps around: the grid holds the velocity's correlation's decay)."""
    R = _cosine_sums(_trapezoid_weights(f) * Sv)
    rho = np.clip(R / R[0], -1.0, 1.0)
    Rd = coulomb_n**2 * (2 / math.pi) * (np.arcsin(rho) - rho)
    Rd[1:-1] *= 2  # the lags -j and j, j = 1..M-1
    return 2 * T * np.maximum(_cosine_sums(Rd), 0.0), math.sqrt(R[0])


def _linearised(plant: Plant, ve: VirtualEnvironment, latency: float, f: np.ndarray,
                G: np.ndarray, b_eq: float, S_drive: np.ndarray, Se: np.ndarray,
                coulomb_n: float, Sd: np.ndarray | None = None) -> tuple:
    """The loop with b + b_eq on the grid ``f`` (``G`` the VE's path there, which b leaves
    alone): (P, sigma_v, S_d), d's spectrum and the velocity's rms settled together (module
    doc). ``S_drive``: the forces entering with the command (excitation, amplifier), ``Se``
    the quantisation error's spectrum; ``Sd`` a first guess of d's (a neighbouring b_eq's)."""
    P, V = linear.held_plant(Plant(plant.m, plant.b + b_eq), ve.T, 2 * math.pi * _off_zero(f),
                             latency)
    VF2 = np.abs(V / (1 + G * P)) ** 2
    base = VF2 * (S_drive + np.abs(G) ** 2 * Se)
    Sd, sigma = (np.zeros_like(f) if Sd is None else Sd), math.inf
    for _ in range(50):  # d is a small share of the velocity: a few rounds settle it
        Sd, new = sign_remnant(f, base + VF2 * Sd, coulomb_n, ve.T)
        if abs(new - sigma) <= _REMNANT_TOL * new:
            break
        sigma = new
    return P, new, Sd


def _friction_loop(plant: Plant, ve: VirtualEnvironment, latency: float, sources: NoiseSources,
                   S_drive_of, f_linear: np.ndarray) -> tuple:
    """(b_eq, f, P, G, S_d, sigma_v) of the self-consistent linearisation (module doc). The
    root lies at or above b_lo = Fc sqrt(2/pi) / sigma_v of the linear loop, so the loop
    with b + b_lo, more damped than any tried, sets the frequency grid of the search (only
    as fine as its poles need: ``frequency_grid``'s ``least`` lowered), and the loop with
    b + b_eq the grid of the spectra returned. ``S_drive_of(f)``: the spectrum of the forces
    entering with the command on a grid."""
    T, fc = ve.T, sources.coulomb_n
    target = fc * friction.SQRT_2_OVER_PI
    white_e = lambda g: np.full_like(g, 2 * T * sources.quantum_m**2 / 12)  # noqa: E731
    path = lambda g: linear.loop_parts(plant, ve, 2 * math.pi * _off_zero(g), latency)[1]  # noqa: E731
    drive = S_drive_of(f_linear)
    if target >= math.sqrt(float(np.sum(_trapezoid_weights(f_linear) * drive))):
        raise UserError(f"Coulomb friction {fc:g} N holds the handle under this excitation "
                        "(Fc sqrt(2/pi) at or above the force that drives it): its force noise "
                        "is not predicted")
    sigma0 = _linearised(plant, ve, latency, f_linear, path(f_linear), 0.0, drive,
                         white_e(f_linear), fc)[1]
    lo = target / sigma0
    f = frequency_grid(Plant(plant.m, plant.b + lo), ve, latency, least=_SEARCH_POINTS)
    G, S_drive, Se = path(f), S_drive_of(f), white_e(f)
    solved = {}

    def excess(b_eq: float) -> float:  # b_eq sigma_v(b + b_eq) rises with b_eq
        if b_eq not in solved:
            last = solved[next(reversed(solved))][2] if solved else None
            solved[b_eq] = _linearised(plant, ve, latency, f, G, b_eq, S_drive, Se, fc, last)
        return b_eq * solved[b_eq][1] - target

    top = friction.B_EQ_MAX - plant.b
    hi = 2.0 * lo
    while excess(hi) < 0:
        if hi >= top:
            raise UserError(f"Coulomb friction {fc:g} N holds the handle under this excitation "
                            "(no damper stands for it): its force noise is not predicted")
        lo, hi = hi, min(4.0 * hi, top)
    # (at lo the excess is <= 0 but for rounding: then lo is the root)
    b_eq = lo if excess(lo) >= 0 else optimize.brentq(excess, lo, hi, xtol=1e-12, rtol=1e-4)
    excess(b_eq)
    out = frequency_grid(Plant(plant.m, plant.b + b_eq), ve, latency)
    G = path(out)
    P, sigma, Sd = _linearised(plant, ve, latency, out, G, b_eq, S_drive_of(out), white_e(out),
                               fc, np.interp(out, f, solved[b_eq][2]))
    return b_eq, out, P, G, Sd, sigma


def frequency_grid(plant: Plant, ve: VirtualEnvironment, latency: float = 0.0,
                   least: int = 1 << 12) -> np.ndarray:
    """M + 1 equally spaced frequencies [Hz] from 0 to 1/(2T), M a power of two of at least
    10 / delta and ``least``, delta = -ln|z| of the loop's least damped pole. A spectrum of the sampled loop
    is even and periodic in f T, so the trapezoid rule over this grid is exact to ~e^(-2 M
    delta) (Trefethen & Weideman, "The exponentially convergent trapezoidal rule", SIAM Rev.
    56(3), 2014): 1e-9 here, however sharp the resonance. UserError when the loop is unstable
    (it has no stationary noise)."""
    lam = np.linalg.eigvals(linear.closed_loop(plant, ve, latency).A)
    if ve.K == 0:  # the position's own integrator (any offset is at rest): no noise sees it
        lam = lam[np.abs(lam - 1.0) > 1e-9]
    radius = np.abs(lam)
    if np.any(radius >= 1.0):
        raise UserError("the loop is unstable: it has no stationary force noise to predict")
    delta = float(np.min(-np.log(np.maximum(radius, 1e-300)))) if len(lam) else 1.0
    M = max(least, 1 << math.ceil(math.log2(10.0 / max(delta, 1e-9))))
    if M > _MAX_POINTS:
        raise UserError(f"the loop's least damped pole (|z| = 1 - {1 - math.exp(-delta):.2g}) "
                        "needs a finer frequency grid than this model takes")
    return np.linspace(0.0, 0.5 / ve.T, M + 1)


def _off_zero(f: np.ndarray) -> np.ndarray:
    """The grid with f = 0 moved a hair up: the loop's transfer functions have their limits
    there, while 0 / 0 (a damper's derivative over the plant's integrator) would be NaN."""
    g = f.copy()
    g[0] = 1e-9 * f[1]
    return g


def _trapezoid_weights(f: np.ndarray) -> np.ndarray:
    h = f[2] - f[1]  # (f[0] may have been moved off zero)
    c = np.full_like(f, h)
    c[0] = c[-1] = 0.5 * h
    return c


def _error_psd(f: np.ndarray, quantum: float, T: float,
               increments: np.ndarray | None) -> tuple[np.ndarray, float | None]:
    """One-sided spectrum [m^2/Hz] of the quantisation error: white (2 T Delta^2 / 12), or
    from rho_j of the stated motion's increments; and rho_1 (None without a motion)."""
    var = quantum**2 / 12
    if increments is None or quantum <= 0:
        return np.full_like(f, 2 * T * var), None
    rho = error_correlation(increments, quantum)
    lags = np.zeros(2 * (len(f) - 1))  # f on the uniform grid: the cosine series is one FFT
    lags[1:len(rho) + 1] = rho[:len(lags) - 1]
    shape = 1 + 2 * np.fft.rfft(lags).real
    return 2 * T * var * np.maximum(shape, 0.0), float(rho[0])


def force_noise(plant: Plant, ve: VirtualEnvironment, sources: NoiseSources,
                band_hz: tuple[float, float] = FELT_BAND_HZ, latency: float = 0.0,
                increments: np.ndarray | None = None,
                excitation: Excitation | None = None) -> ForceNoise:
    """The force noise of the loop (module doc), RMS in ``band_hz`` [Hz] and spectra.

    ``excitation``: the white force that moves the handle (``Excitation``); needed with
    Coulomb friction (``sources.coulomb_n``), whose part depends on the motion. ``increments``:
    the motion's D_j (``increments_from_excitation`` / ``_from_speed``) for the quantisation
    error's colour; None takes them from ``excitation`` through the (linearised) loop, or,
    without one, the error as white (the model for motion faster than ``white_speed``).
    UserError where the loop is unstable, or where friction holds the handle.
    """
    lo, hi = (float(band_hz[0]), float(band_hz[1]))
    if not (0 <= lo < hi and math.isfinite(hi)):
        raise UserError(f"noise band must be 0 <= low < high (finite) Hz, got {band_hz!r}")
    if sources.coulomb_n and excitation is None:
        raise UserError("Coulomb friction's force noise depends on the motion: state the "
                        "excitation that moves the handle")
    T = ve.T
    nyq = 0.5 / T
    f = frequency_grid(plant, ve, latency)
    Sn_of = lambda g: np.full_like(g, 2 * T * sources.force_noise_n**2)  # noqa: E731
    fr = None
    if sources.coulomb_n:
        b_eq, f, P, G, Sd, sigma_v = _friction_loop(
            plant, ve, latency, sources, lambda g: excitation.psd(g, T) + Sn_of(g), f)
    else:
        b_eq, Sd = 0.0, np.zeros_like(f)
        P, G = linear.loop_parts(plant, ve, 2 * math.pi * _off_zero(f), latency)
    felt_plant = Plant(plant.m, plant.b + b_eq)
    if increments is None and excitation is not None:
        increments = increments_from_excitation(felt_plant, ve, excitation.std_n, latency,
                                                band_hz=excitation.band_hz)
    one_plus_L = 1 + G * P
    Se, rho1 = _error_psd(f, sources.quantum_m, T, increments)
    Sn = Sn_of(f)
    q_part = np.abs(G / one_plus_L) ** 2 * Se
    through = np.abs(G * P / one_plus_L) ** 2  # a force entering with the command, to it
    n_part = Sn / np.abs(one_plus_L) ** 2
    d_part = through * Sd
    psd_command = q_part + through * Sn + d_part
    psd_force = q_part + n_part + d_part

    rms_command = math.sqrt(_band_integral(f, psd_command, lo, min(hi, nyq)))
    parts = {"quantisation": math.sqrt(_held_band(f, q_part, lo, hi, T)),
             "amplifier": math.sqrt(_held_band(f, n_part, lo, hi, T)),
             "friction": math.sqrt(_held_band(f, d_part, lo, hi, T))}
    rms_felt = math.sqrt(sum(v**2 for v in parts.values()))
    white = increments is None or rho1 is None or rho1 < WHITE_RHO
    model = ("exact sampled loop (labbench.model.linear) with "
             + ("white quantisation error (Bennett 1948)" if increments is None else
                "the quantisation error of the stated motion (Widrow & Kollar ch. 11)"))
    if sources.coulomb_n:
        applied = (excitation.psd(f, T) + Sn + np.abs(G) ** 2 * Se + np.abs(G * P) ** 2 * Sd) \
            / np.abs(one_plus_L) ** 2
        u_rms = math.sqrt(float(np.sum(_trapezoid_weights(f) * applied)))
        fr = FrictionPart(sources.coulomb_n, b_eq, sigma_v, u_rms,
                          -math.expm1(-sources.coulomb_n**2 / (2 * u_rms**2)), excitation.std_n)
        model += (f"; Coulomb friction {sources.coulomb_n:.3g} N under {excitation.std_n:.3g} N "
                  f"of white excitation: its equivalent damper {b_eq:.3g} N s/m (Booton 1954) "
                  "and its remnant by the arcsine law (Van Vleck & Middleton 1966)")
    return ForceNoise(
        f_hz=f, psd_command=psd_command, psd_force=psd_force, band_hz=(lo, hi),
        rms_command=rms_command, rms_felt=rms_felt,
        rms_command_total=math.sqrt(float(np.sum(_trapezoid_weights(f) * psd_command))),
        parts=parts, white=white, rho1=rho1, model=model, friction=fr)


def _band_integral(f: np.ndarray, psd: np.ndarray, lo: float, hi: float) -> float:
    """Integral of ``psd`` over [lo, hi] (within the grid), the edges interpolated."""
    lo, hi = max(lo, f[0]), min(hi, f[-1])
    if hi <= lo:
        return 0.0
    inside = (f > lo) & (f < hi)
    g = np.concatenate([[lo], f[inside], [hi]])
    p = np.concatenate([[np.interp(lo, f, psd)], psd[inside], [np.interp(hi, f, psd)]])
    return float(np.trapezoid(p, g))


def _held_band(f: np.ndarray, psd: np.ndarray, lo: float, hi: float, T: float) -> float:
    """Power of the held (continuous) force in [lo, hi] Hz: the image band around k / T holds
    the sampled spectrum at |g - k / T|, times sinc^2(g T) (module doc)."""
    weighted = lambda g: psd * np.sinc(g * T) ** 2  # noqa: E731 - the spectrum seen at g
    total = _band_integral(f, weighted(f), lo, hi)
    k = 1
    while k / T - f[-1] < hi:
        for sign in (-1, 1):  # g = k / T + sign f, f = sign (g - k / T)
            a, b = sorted((sign * (lo - k / T), sign * (hi - k / T)))
            total += _band_integral(f, weighted(k / T + sign * f), a, b)
        k += 1
    return total
