"""Closed-loop impedance of an impedance-type haptic display: paper model and exact sampled model.

Two models of the same loop (signs and units: docs/conventions.md):

* the paper's continuous model, Colonnese, Sketch & Okamura, "Closed-loop
  stiffness and damping accuracy of impedance-type haptic displays", eq. 2
  (its spring, damper and spring-damper cases are eqs. 4, 6, 7), with the
  zero-order hold approximated by a delay of T/2;
* the exact sampled-data model: plant ``m x'' + b x' = f_exo - f_ve``
  driven through a zero-order hold, ``x[k]`` sampled at the start of step k,
  velocity ``v[k] = a v[k-1] + (1 - a)(x[k] - x[k-1]) / T`` with
  ``a = exp(-w0 T)``, VE force ``f[k] = K x[k] + B v[k]`` applied during step
  ``k + n`` (``td = n T``), ``f_exo[k]`` applied during step k. Its impedance
  ``F_exo(e^{jwT}) / (jw X(e^{jwT}))`` is what an ETFE of sampled force and
  position converges to.

  ``latency`` [s] (any value >= 0, fractions of a sample included) extends it
  with the rig's own actuator delay on the whole command ``u[k] = f_exo[k] -
  f[k - n]`` (amplifier, transport, filters: what a bench adds beyond the
  software's ``td``). With ``latency = (d + alpha) T``, 0 <= alpha < 1, the
  plant holds ``u[k - d - 1]`` for the first ``alpha T`` of step k and
  ``u[k - d]`` for the rest, so one step is ``x+ = Ad x + G_late u[k - d] +
  G_early u[k - d - 1]`` with ``G_late = Gamma((1 - alpha) T)``, ``G_early =
  e^{A (1 - alpha) T} Gamma(alpha T)`` (``G_late + G_early = Bd``): the
  modified z-transform of the held input (Franklin, Powell & Workman sec. 4.3.4
  on fractional delays). ``labbench.analysis.loopfit`` fits it to a measured Z.

Bandwidths read off measured curves live in ``labbench.model.effective``; this
module holds the formulas.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import null_space

from labbench.errors import UserError
from labbench.model.ve import RANGES, Plant, VirtualEnvironment

MODELS = ("paper", "sampled")

# Eigenvalues of the loop matrix this close to z = 1 are found again as roots of the
# characteristic polynomial in w = z - 1 (``_poles_near_one``): there a float eigenvalue's
# error (~1e-16 |A|) can exceed its distance from the unit circle (a soft spring on a
# heavily damped device: 1 - |z| ~ K T / b). Only those whose |z| is within
# _UNDECIDED of 1 need it: an eigenvalue's error stays below ~1e-8 even in a close pair.
_NEAR_ONE = 1e-2
_UNDECIDED = 1e-6


# ----------------------------------------------------------------------------- paper model
def _ve_paper(ve: VirtualEnvironment, s: np.ndarray) -> np.ndarray:
    """VE(s) of eq. 2: K + B s w0 / (s + w0) (the filter is 1 when w0 is infinite)."""
    lowpass = 1.0 if math.isinf(ve.w0) else ve.w0 / (s + ve.w0)
    return ve.K + ve.B * s * lowpass


def z_paper(plant: Plant, ve: VirtualEnvironment, w, latency: float = 0.0) -> np.ndarray:
    """Closed-loop impedance Z(jw) = F/V of the paper's eq. 2.

    ``Z(s) = (m s^2 + b s + VE(s) e^{-s(T/2 + td)}) / s``; for ``ve.kind ==
    "none"`` this is the open-loop device ``m s + b``.

    ``latency`` [s]: the device's own delay on the whole command (module doc). The
    excitation is commanded through the device too, so what an ETFE of the recorded
    command converges to is ``e^{s latency} (m s + b) + VE(s) e^{-s(T/2 + td)} / s``:
    ``e^{s latency}`` times eq. 2 with td + latency, the impedance a force applied at
    the handle itself (a hand) feels. Both have the same poles: stability and K_max
    are those of eq. 2 with td + latency. The exact sampled model has the same
    structure (``z_sampled``).
    """
    s = 1j * np.asarray(w, dtype=float)
    d = np.exp(-s * ve.delay)  # eq. 8
    plant_term = plant.m * s + plant.b
    if latency:
        plant_term = plant_term * np.exp(s * latency)
    return plant_term + _ve_paper(ve, s) * d / s


# ----------------------------------------------------------------------------- sampled model
# frequencies per block of z_sampled: its chain of complex temporaries stays in the cache (at
# the 900 000 bins of a 30-minute record, all at once cost 23x their time at 60 000)
FREQ_BLOCK = 1 << 14


def zoh_matrices(m: float, b: float, T: float) -> tuple[np.ndarray, np.ndarray]:
    """(Ad, Bd) of the state [x, x'] of ``m x'' + b x' = u`` for u held constant over T.

    The exact discretisation, the matrix exponential of the augmented system
    (Franklin, Powell & Workman, Digital Control of Dynamic Systems, sec. 4.3),
    in closed form for this plant: with z = b T / m,
    ``Ad = [[1, T p1], [0, e^-z]]``, ``Bd = [T^2 p2, T p1] / m``,
    ``p1 = (1 - e^-z) / z``, ``p2 = (z - 1 + e^-z) / z^2`` (1 and 1/2 at b = 0),
    by their Taylor series below z = 0.01 where the closed forms cancel (series
    error < 1e-20; above, rounding < 1e-13 relative). ~100x cheaper than ``expm``,
    which the closed-loop fit calls thousands of times.
    """
    z = b * T / m
    if z < 1e-2:
        k = np.arange(8)
        terms = (-z) ** k
        p1 = float(np.sum(terms / _FACT[k + 1]))
        p2 = float(np.sum(terms / _FACT[k + 2]))
    else:
        p1 = -math.expm1(-z) / z
        p2 = (z + math.expm1(-z)) / z**2
    Ad = np.array([[1.0, T * p1], [0.0, math.exp(-z)]])
    return Ad, np.array([T * T * p2, T * p1]) / m


_FACT = np.array([math.factorial(k) for k in range(10)], float)


def latency_split(latency: float, T: float) -> tuple[int, float]:
    """(d, alpha): latency = (d + alpha) T with d whole and 0 <= alpha < 1 (alpha within
    1e-9 of 0 or 1 snaps to the whole sample)."""
    if not (latency >= 0 and math.isfinite(latency)):
        raise UserError(f"latency must be a finite number >= 0 s, got {latency!r}")
    d = math.floor(latency / T + 1e-9)
    alpha = latency / T - d
    return d, (0.0 if abs(alpha) < 1e-9 else alpha)


def latency_inputs(plant: Plant, T: float, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """(G_late, G_early): input vectors of u[k - d] and u[k - d - 1] over one step (module doc)."""
    Ad_late, G_late = zoh_matrices(plant.m, plant.b, (1 - alpha) * T)
    if alpha == 0.0:
        return G_late, np.zeros(2)
    _, G_a = zoh_matrices(plant.m, plant.b, alpha * T)
    return G_late, Ad_late @ G_a


def _plant_response(plant: Plant, T: float, w: np.ndarray, latency: float = 0.0) -> np.ndarray:
    """P(e^{jwT}) = X/U of the ZOH-sampled plant, [1 0](zI - Ad)^{-1} G(z), with
    G = Bd without latency, else z^-d (G_late + G_early z^-1) (module doc)."""
    return _held(plant, T, w, latency, False)[0]


def held_plant(plant: Plant, T: float, w, latency: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(X/U, V/U) of the held plant at ``w`` [rad/s]: the position and the velocity at the
    sample instants per held command, the rows of (zI - Ad)^{-1} G(z) (``_plant_response``).
    Ad's velocity row does not see the position (a10 = 0), so V/U = g1(z) / (z - a11), g1 the
    velocity's share of G(z)."""
    return _held(plant, T, np.asarray(w, dtype=float), latency, True)


def _held(plant: Plant, T: float, w: np.ndarray, latency: float, velocity: bool) -> tuple:
    Ad, _ = zoh_matrices(plant.m, plant.b, T)
    d, alpha = latency_split(latency, T)
    g_late, g_early = latency_inputs(plant, T, alpha)
    z = np.exp(1j * w * T)
    zinv = 1.0 / z  # |z| = 1: exact to rounding, and a complex exp saved
    late = np.exp(-1j * w * (d * T)) if d else 1.0  # z^-d: a complex power costs 3x an exp
    g0 = (g_late[0] + g_early[0] * zinv) * late
    g1 = (g_late[1] + g_early[1] * zinv) * late
    # z - Ad[0,0] as expm1 + (1 - Ad[0,0]): no cancellation near w = 0 (and so z - Ad[1,1])
    em1 = np.expm1(1j * w * T)
    z_minus_a00 = em1 + (1.0 - Ad[0, 0])
    z_minus_a11 = em1 + (1.0 - Ad[1, 1]) if velocity else z - Ad[1, 1]
    P = (z_minus_a11 * g0 + Ad[0, 1] * g1) / (z_minus_a00 * z_minus_a11 - Ad[0, 1] * Ad[1, 0])
    return P, (g1 / z_minus_a11 if velocity else None)


def _ve_sampled(ve: VirtualEnvironment, w: np.ndarray) -> np.ndarray:
    """C(e^{jwT}) = F/X of the sampled VE: K + B (1-a)(1 - z^-1) / (T (1 - a z^-1))."""
    a = ve.filter_pole
    one_minus_zinv = -np.expm1(-1j * w * ve.T)
    velocity = (1 - a) * one_minus_zinv / (ve.T * (1 - a * np.exp(-1j * w * ve.T)))
    return ve.K + ve.B * velocity


def z_sampled(plant: Plant, ve: VirtualEnvironment, w, latency: float = 0.0,
              ve_delay: float | None = None) -> np.ndarray:
    """Exact sampled-data impedance F_exo(e^{jwT}) / (jw X(e^{jwT})).

    From ``x = P (f_exo - z^-n C x)`` (module docstring):
    ``Z = 1 / (jw P) + z^-n C / (jw)``, the sampled counterpart of eq. 2; with an
    actuator ``latency`` P carries it (module doc). Raises UserError when td is
    not a whole number of samples.

    ``ve_delay`` [s] (fractions of a sample allowed) replaces the VE's td: the VE
    force reaches the plant ``latency + ve_delay`` after its sample, the excitation
    ``latency`` after its own, so ``x = P_L f_exo - P_{L+tv} C x`` and
    ``Z = (1 + P_{L+tv} C) / (jw P_L)``, P_d the held plant with the input delayed by d
    (the fractional split of ``latency_split``); for a whole tv = nT,
    ``P_{L+tv} = z^-n P_L`` and this is the td form above.
    """
    w = np.asarray(w, dtype=float)
    if w.ndim == 1 and len(w) > FREQ_BLOCK:  # block by block: a long record's every bin
        return np.concatenate([z_sampled(plant, ve, w[i:i + FREQ_BLOCK], latency, ve_delay)
                               for i in range(0, len(w), FREQ_BLOCK)])
    jw = 1j * w
    p_l = _plant_response(plant, ve.T, w, latency)
    Z = 1.0 / (jw * p_l)
    if ve.kind != "none":
        if ve_delay is None:
            path = np.exp(-1j * w * ve.delay_samples * ve.T)
        else:
            path = _plant_response(plant, ve.T, w, latency + ve_delay) / p_l
        Z = Z + path * _ve_sampled(ve, w) / jw
    return Z


def loop_parts(plant: Plant, ve: VirtualEnvironment, w,
               latency: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(P, G) of the exact sampled loop at e^{jwT}: P = X/U, the held plant with the device's
    ``latency`` on the command, and G = z^-n C, the VE's path from the sampled position to the
    command (its td and velocity filter). The loop gain is G P, and ``z_sampled`` is
    (1 + G P) / (jw P). Raises UserError when td is not whole samples."""
    w = np.asarray(w, dtype=float)
    P = _plant_response(plant, ve.T, w, latency)
    if ve.kind == "none":
        return P, np.zeros_like(P)
    return P, np.exp(-1j * w * ve.delay_samples * ve.T) * _ve_sampled(ve, w)


def theory_curve(plant: Plant, ve: VirtualEnvironment, w, model: str = "paper",
                 latency: float = 0.0) -> np.ndarray:
    """Z(jw) of the chosen model ("paper" or "sampled"), with the device's own delay
    ``latency`` [s] on the whole command."""
    if model == "paper":
        return z_paper(plant, ve, w, latency)
    if model == "sampled":
        return z_sampled(plant, ve, w, latency)
    raise ValueError(f"unknown model {model!r}; choose one of {', '.join(MODELS)}")


@dataclass(frozen=True)
class DiscreteLoop:
    """The exact sampled loop as ``s[k+1] = A s[k] + B f_exo[k]``, ``x[k] = C s[k] + D f_exo[k]``.

    State ``s[k] = [x[k], x'[k], x[k-1], v[k-1], f[k-1], ..., f[k-n], u[k-1], ...,
    u[k-D]]`` (plant position and velocity at the start of step k, previous
    sample, previous velocity estimate, VE forces still in the delay line, and
    with an actuator latency the D commands still in flight). ``as_dlti()``
    gives the tuple ``scipy.signal.dlsim`` takes.
    """

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray
    T: float

    def as_dlti(self) -> tuple:
        return (self.A, self.B, self.C, self.D, self.T)


def closed_loop(plant: Plant, ve: VirtualEnvironment, latency: float = 0.0) -> DiscreteLoop:
    """State-space form of the exact sampled loop (input f_exo[k], output x[k]);
    ``latency`` [s]: the actuator delay on the command (module doc)."""
    n = ve.delay_samples
    T, a = ve.T, ve.filter_pole
    Ad, _ = zoh_matrices(plant.m, plant.b, T)
    d, alpha = latency_split(latency, T)
    g_late, g_early = latency_inputs(plant, T, alpha)
    n_u = d + (alpha > 0)  # commands in flight
    size = 4 + n + n_u
    X, XD, XP, VP, F0, U0 = 0, 1, 2, 3, 4, 4 + n
    # f[k] = K x[k] + B (a v[k-1] + (1 - a)(x[k] - x[k-1]) / T) as a row on s[k]
    force = np.zeros(size)
    force[X] = ve.K + ve.B * (1 - a) / T
    force[XP] = -ve.B * (1 - a) / T
    force[VP] = ve.B * a
    applied = force if n == 0 else np.eye(size)[F0 + n - 1]  # f[k - n]
    # u[k - j] as (row on s[k], coefficient of f_exo[k])
    def command(j):
        return (-applied, 1.0) if j == 0 else (np.eye(size)[U0 + j - 1], 0.0)

    A = np.zeros((size, size))
    B = np.zeros((size, 1))
    A[:2, :2] = Ad
    for g, j in ((g_late, d), (g_early, d + 1)):
        if g.any():
            row, coef = command(j)
            A[:2, :] += np.outer(g, row)
            B[:2, 0] += g * coef
    A[XP, X] = 1.0
    A[VP, X], A[VP, XP], A[VP, VP] = (1 - a) / T, -(1 - a) / T, a
    if n:
        A[F0] = force
        for i in range(1, n):
            A[F0 + i, F0 + i - 1] = 1.0
    if n_u:
        A[U0], B[U0, 0] = command(0)
        for i in range(1, n_u):
            A[U0 + i, U0 + i - 1] = 1.0
    C = np.zeros((1, size))
    C[0, X] = 1.0
    return DiscreteLoop(A=A, B=B, C=C, D=np.zeros((1, 1)), T=T)


# ----------------------------------------------------------------------------- stability
@dataclass(frozen=True)
class Stability:
    """``stable``: every pole of the exact sampled loop strictly inside the unit circle;
    ``spectral_radius`` the largest |z|; ``margin`` 1 - that radius, computed without
    the rounding of |z| near 1 (what ``stable`` is decided on: ``margin > 0``)."""

    stable: bool
    spectral_radius: float
    margin: float


def stability(plant: Plant, ve: VirtualEnvironment, latency: float = 0.0) -> Stability:
    """Stability of the exact sampled loop: every pole inside the unit circle.

    The poles are the eigenvalues of the loop matrix A (``closed_loop``), except those
    within ``_NEAR_ONE`` of z = 1 and ``_UNDECIDED`` of the unit circle, which are polished
    as roots of the characteristic
    polynomial in w = z - 1 (``_poles_near_one``), whose coefficients carry no
    cancellation. So there is no threshold: a soft spring on a heavily damped device
    (a pole at 1 - 1e-10) is stable, and ``k_max`` (which calls this) finds the true
    boundary, not one shifted by a tolerance.

    Without a virtual spring (K = 0) any constant position offset is an equilibrium:
    A has the eigenvector e = [1, 0, 1, 0, 0, ...] (x = x[k-1] = const, all velocities
    and forces zero) with eigenvalue exactly 1. That mode is not instability, so it is
    deflated: with Q an orthonormal basis of the complement of e, ``Q^T A Q`` carries
    the remaining eigenvalues (Schur deflation, Golub & Van Loan, Matrix Computations,
    sec. 7.3); the polynomial drops its factor w likewise.
    """
    A = closed_loop(plant, ve, latency).A
    if ve.K == 0:
        e = np.zeros(A.shape[0])
        e[0] = e[2] = 1.0
        Q = null_space(e[None, :])
        A = Q.T @ A @ Q
    lam = np.linalg.eigvals(A)
    near = (np.abs(lam - 1.0) < _NEAR_ONE) & (np.abs(1.0 - np.abs(lam)) < _UNDECIDED)
    margins = [1.0 - np.abs(lam[~near])]
    radii = [np.abs(lam[~near])]
    if near.any():
        w = _poles_near_one(plant, ve, latency, lam[near] - 1.0)
        radius = np.abs(1.0 + w)
        # 1 - |1 + w| = -(2 Re w + |w|^2) / (1 + |1 + w|): no rounding of |1 + w| to 1
        margins.append(-(2.0 * w.real + np.abs(w) ** 2) / (1.0 + radius))
        radii.append(radius)
    margin = float(np.min(np.concatenate(margins)))
    return Stability(stable=margin > 0, spectral_radius=float(np.max(np.concatenate(radii))),
                     margin=margin)


def characteristic_polynomial(plant: Plant, ve: VirtualEnvironment,
                              latency: float = 0.0) -> np.ndarray:
    """Coefficients (lowest power first) of the loop's characteristic polynomial in
    w = z - 1, the equilibrium factor w divided out when K = 0.

    From ``1 + z^-n C(z) P_L(z) = 0`` (module doc) with ``P_L = z^-(d+1) N(z) /
    ((z - 1)(z - e))``, ``N(z) = (z - e)(G_late,0 z + G_early,0) + Ad01 (G_late,1 z +
    G_early,1)``, ``e = exp(-b T / m)``, ``C = (K T (z - a) + B (1 - a)(z - 1)) / (T (z - a))``:
    ``w (w + 1 - e) T (w + 1 - a) (1 + w)^(n+d+1) + (K T (1 - a) + (K T + B (1 - a)) w) N``.
    Every factor has non-negative coefficients in w (1 - e and 1 - a by expm1), so each
    coefficient is a sum of positive terms, accurate to rounding: the small roots, the poles
    near z = 1, are as accurate as the model's numbers.
    """
    P = np.polynomial.polynomial
    T = ve.T
    n = ve.delay_samples
    d, alpha = latency_split(latency, T)
    Ad, _ = zoh_matrices(plant.m, plant.b, T)
    g_late, g_early = latency_inputs(plant, T, alpha)
    one_minus_e = -math.expm1(-plant.b * T / plant.m)
    one_minus_a = 1.0 if math.isinf(ve.w0) else -math.expm1(-ve.w0 * T)
    N = P.polyadd(P.polymul([one_minus_e, 1.0], [g_late[0] + g_early[0], g_late[0]]),
                  Ad[0, 1] * np.array([g_late[1] + g_early[1], g_late[1]]))
    hold = P.polymul(P.polymul([one_minus_e * T, T], [one_minus_a, 1.0]),
                     P.polypow([1.0, 1.0], n + d + 1))
    gain = [ve.K * T * one_minus_a, ve.K * T + ve.B * one_minus_a]
    if ve.K == 0:  # w divides both terms: gain = [0, B (1 - a)], hold = w (...)
        return P.polyadd(hold, ve.B * one_minus_a * N)
    return P.polyadd(P.polymul([0.0, 1.0], hold), P.polymul(gain, N))


def _poles_near_one(plant: Plant, ve: VirtualEnvironment, latency: float,
                    start: np.ndarray) -> np.ndarray:
    """The poles w = z - 1 near 0, polished from the eigenvalues ``start`` (also w) on the
    characteristic polynomial by Newton's method with implicit deflation of the others
    (Maehly; Stoer & Bulirsch, Introduction to Numerical Analysis, sec. 5.5), so close or
    double poles converge to distinct roots. The starts are nudged off the real axis,
    differently each, so a pair that is complex (or real) may become so."""
    P = np.polynomial.polynomial
    c = characteristic_polynomial(plant, ve, latency)
    c = c / np.max(np.abs(c))  # no overflow in the sums below
    dc = P.polyder(c)
    scale = max(float(np.max(np.abs(start))), 1e-300)
    w = start.astype(complex) + 1j * scale * 1e-3 * np.arange(1, start.size + 1)
    for _ in range(100):
        p = P.polyval(w, c)
        apart = w[:, None] - w[None, :]
        np.fill_diagonal(apart, np.inf)
        # p / (p' - p sum_j 1/(w_i - w_j)): Newton's step on p / prod_j (w - w_j)
        denominator = P.polyval(w, dc) - p * np.sum(1.0 / apart, axis=1)
        ok = (p != 0) & (denominator != 0)
        step = np.where(ok, p / np.where(ok, denominator, 1.0), 0.0)
        w = w - step
        if np.all(np.abs(step) <= 4e-16 * np.abs(w)):
            break
    return w


def _stable_with_k(plant: Plant, ve: VirtualEnvironment, K: float, latency: float = 0.0) -> bool:
    return stability(plant, ve.with_(K=K), latency).stable


def k_max(plant: Plant, ve: VirtualEnvironment, rel_tol: float = 1e-4, latency: float = 0.0) -> float | None:
    """Largest K keeping the exact sampled loop stable (other parameters fixed).

    Defined as the first loss of stability as K grows from 0. Stability changes only at a
    K that puts a pole on the unit circle (``_crossings``): the first of them the loop is
    stable just below and unstable just above (0.1 %) is bisected to ``rel_tol`` (default
    0.01 %, as docs/theory.md states; ``stability`` decides each K, with no tolerance).
    Where that finds nothing, K is raised by factors of 1.25 from a small value until the
    loop is unstable and that bracket bisected. Either way every K checked below the result
    is stable. ~8 stability checks instead of ~70 (the design page redraws at a slider
    move). 0.0 when even a tiny K is unstable; ``math.inf`` when no K up to the
    stiffest VE there is (``labbench.model.ve.RANGES``, 1e7 N/m) is unstable; None for kinds
    without a spring.
    """
    if ve.kind not in ("spring", "spring-damper"):
        return None
    ceiling = RANGES["K"][1]
    guess = k_max_approx(plant, ve, latency)
    lo = min(1e-6 * guess if guess and math.isfinite(guess) else 1e-6, 1e-6 * ceiling)
    if not _stable_with_k(plant, ve, lo, latency):
        return 0.0
    for K in _crossings(plant, ve, latency, lo, ceiling):
        # stability changes only where a pole is on the unit circle: the first crossing
        # that leaves the loop unstable just above it is the boundary (one that touches
        # the circle and returns does not); any doubt, and the scan below decides
        near_lo, near_hi = K * (1 - _BRACKET), min(K * (1 + _BRACKET), ceiling)
        if not _stable_with_k(plant, ve, near_lo, latency):
            break
        if not _stable_with_k(plant, ve, near_hi, latency):
            return _bisect_k(plant, ve, near_lo, near_hi, rel_tol, latency)
    hi = lo * 1.25
    while _stable_with_k(plant, ve, hi, latency):
        if hi >= ceiling:
            return math.inf
        lo, hi = hi, min(hi * 1.25, ceiling)
    return _bisect_k(plant, ve, lo, hi, rel_tol, latency)


def _bisect_k(plant, ve, lo: float, hi: float, rel_tol: float, latency: float) -> float:
    """The largest stable K of the bracket [lo stable, hi unstable], to ``rel_tol``."""
    while hi - lo > rel_tol * lo:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if _stable_with_k(plant, ve, mid, latency) else (lo, mid)
    return lo


_BRACKET = 1e-3  # relative half-width of the bracket around a crossing that k_max bisects
_CROSSING_GRID = 4096
_REFINE_STEPS = 8


def _crossings(plant: Plant, ve: VirtualEnvironment, latency: float, lo: float,
               hi: float) -> list[float]:
    """The stiffnesses K in (lo, hi] at which a pole of the loop lies on the unit circle,
    ascending: the real values of K = -(z^n / P(z) + B v(z)) on z = e^{j theta} (the
    characteristic equation 1 + z^-n (K + B v) P = 0 solved for K), where its imaginary part
    changes sign on a grid of theta, refined together by regula falsi (well within the
    bracket ``k_max`` checks around it). A root missed (two within one grid step)
    or misplaced shows as a check that disagrees, and ``k_max`` falls back to its scan."""
    T, n = ve.T, ve.delay_samples

    def h(theta):
        w = np.asarray(theta, float) / T
        P = _plant_response(plant, T, w, latency)
        return -(np.exp(1j * w * T * n) / P + ve.B * _ve_sampled(ve.with_(K=0.0, B=1.0), w))

    # linear, and log-spaced towards 0 where a soft spring on a heavy handle crosses
    theta = np.union1d(np.linspace(0.0, math.pi, _CROSSING_GRID + 1)[1:],
                       np.geomspace(1e-9, math.pi, _CROSSING_GRID // 4))
    with np.errstate(all="ignore"):
        im = h(theta).imag
        i = np.flatnonzero(np.isfinite(im[:-1]) & np.isfinite(im[1:])
                           & (np.sign(im[:-1]) * np.sign(im[1:]) < 0))
        # each bracket narrowed together by the Illinois variant of regula falsi (Dowell &
        # Jarratt, BIT 11, 1971): superlinear, and never leaves its bracket
        a, b, fa, fb = theta[i], theta[i + 1], im[i], im[i + 1]
        for _ in range(_REFINE_STEPS):
            c = b - fb * (b - a) / (fb - fa)
            fc = h(c).imag
            same = np.sign(fc) == np.sign(fb)
            fa = np.where(same, 0.5 * fa, fb)
            a = np.where(same, a, b)
            b, fb = c, fc
        K = h(np.append(b, math.pi)).real
    # z = -1 (theta = pi) is real by symmetry: a crossing there too
    K = K if im[-1] == 0.0 else K[:-1]
    return sorted(float(k) for k in K if math.isfinite(k) and lo < k <= hi)


def k_max_approx(plant: Plant, ve: VirtualEnvironment, latency: float = 0.0) -> float | None:
    """The paper's approximate stability boundary, solved for K.

    Spring: ``b > K (T/2 + td)`` (paper sec. 3.1, after Gil et al. 2009), so
    ``K_max ~ b / (T/2 + td)``. Spring-damper: the same condition on the
    low-frequency effective damping ``b + B - K (T/2 + td) > 0`` (paper
    sec. 3.3), ``K_max ~ (b + B) / (T/2 + td)``; it ignores the velocity
    filter, so compare it with ``k_max``. None for kinds without a spring. An
    actuator ``latency`` adds to the delay.
    """
    if ve.kind == "spring":
        return plant.b / (ve.delay + latency)
    if ve.kind == "spring-damper":
        return (plant.b + ve.B) / (ve.delay + latency)
    return None


# ----------------------------------------------------------------------------- bandwidths, delay
def predicted_ws_star(plant: Plant, ve: VirtualEnvironment) -> float | None:
    """Effective-stiffness bandwidth sqrt(K/m) (paper eq. 5); None without a spring."""
    return math.sqrt(ve.K / plant.m) if ve.K > 0 else None


def predicted_wb_star(ve: VirtualEnvironment) -> float | None:
    """Effective-damping bandwidth w0 (paper sec. 3.2); None without filter or virtual damping."""
    return ve.w0 if ve.B > 0 and math.isfinite(ve.w0) else None


def predicted_bandwidths(plant: Plant, ve: VirtualEnvironment, model: str = "sampled",
                         latency: float = 0.0, n: int = 4000) -> dict:
    """``{"ws_star", "wb_star"}`` [rad/s] read off the model's own ES and ED curves with the
    rules used on measurements (``labbench.model.effective.measured_ws_star`` /
    ``measured_wb_star``), on a log grid of ``n`` points from 1e-3 of the slowest rate
    of the loop to 0.999 of Nyquist (None where the curve never crosses).

    With the exact sampled model this is what a measurement should show: its damping
    falls well before w0 (on the paper's demo, K = 50, B = 1, w0 = 125 rad/s at 1 kHz,
    wb* = 72.6 rad/s), where ``predicted_wb_star`` (w0, paper sec. 3.2) and
    ``predicted_ws_star`` (eq. 5) are the continuous model's closed forms.
    ``latency``: the device's own delay [s] on the whole command (``theory_curve``).
    """
    from labbench.model.effective import effective_impedances, measured_wb_star, measured_ws_star

    rates = [r for r in (predicted_ws_star(plant, ve), ve.w0 if math.isfinite(ve.w0) else None,
                         (plant.b + ve.B) / plant.m) if r]
    w = np.geomspace(1e-3 * min(rates + [1.0 / ve.T]), 0.999 * math.pi / ve.T, n)
    Z = theory_curve(plant, ve, w, model, latency)
    eff = effective_impedances(w, Z)
    return {"ws_star": measured_ws_star(w, eff.ES), "wb_star": measured_wb_star(w, eff.ED, plant.b)}


def low_frequency(plant: Plant, ve: VirtualEnvironment, model: str,
                   latency: float = 0.0) -> tuple[float, float]:
    """(ED, EM) in the limit w -> 0, by Richardson extrapolation in w^2.

    Re Z and Im Z / w are even in w, so ``(4 f(w) - f(2w)) / 3`` removes the
    w^2 term; w is 1e-3 of the loop's fastest relevant rate.
    """
    rates = [1.0 / (ve.delay + latency)]
    if ve.K > 0:
        rates.append(math.sqrt(ve.K / plant.m))
    if math.isfinite(ve.w0):
        rates.append(ve.w0)
    if plant.b + ve.B > 0:
        rates.append((plant.b + ve.B) / plant.m)
    w = 1e-3 * min(rates) * np.array([1.0, 2.0])
    Z = theory_curve(plant, ve, w, model, latency)
    ED, EM = Z.real, Z.imag / w
    return float((4 * ED[0] - ED[1]) / 3), float((4 * EM[0] - EM[1]) / 3)


def delay_effects(plant: Plant, ve: VirtualEnvironment, latency: float = 0.0) -> dict:
    """Low-frequency effect of delay, as numbers, for both models.

    Spring, spring-damper: ``ED_low`` (w -> 0) and its drop below b + B,
    beside the paper's prediction ``K_tau = K (T/2 + td)`` (secs. 3.1, 3.3)
    and ``K_td = K td``. Damper: ``EM_low`` and its drop below the no-delay
    value m - B/w0 (paper model), beside ``B_tau = B (T/2 + td)`` (sec. 3.2)
    and ``B_td``. Sampled-model entries are None when td is not a whole
    number of samples.

    In the sampled model the exogenous force passes through the same hold as
    the VE force, so ``Z_sampled ~ e^{jwT/2} Z_paper`` and its ED drop is close
    to K td rather than K (T/2 + td).

    ``latency`` (the device's own delay, ``theory_curve``) is in both models'
    curves. It leaves the measured low-frequency ED drop unchanged to first order (the
    excitation is delayed with the VE force: ``e^{s latency}`` on the plant's term),
    though a hand at the handle feels K (T/2 + td + latency): ``K_tau_felt``.
    """
    out: dict = {"tau": ve.delay}
    whole = whole_samples(ve)
    if ve.K > 0:
        base = plant.b + ve.B
        out.update(K_tau=ve.K * ve.delay, K_td=ve.K * ve.td)
        if latency:
            out["K_tau_felt"] = ve.K * (ve.delay + latency)
        for model in MODELS:
            ed = low_frequency(plant, ve, model, latency)[0] if model == "paper" or whole else None
            out[f"ED_low_{model}"] = ed
            out[f"ED_drop_{model}"] = None if ed is None else base - ed
    elif ve.B > 0:
        base = plant.m - (0.0 if math.isinf(ve.w0) else ve.B / ve.w0)
        out.update(EM_nodelay=base, B_tau=ve.B * ve.delay, B_td=ve.B * ve.td)
        for model in MODELS:
            em = low_frequency(plant, ve, model, latency)[1] if model == "paper" or whole else None
            out[f"EM_low_{model}"] = em
            out[f"EM_drop_{model}"] = None if em is None else base - em
    return out


def whole_samples(ve: VirtualEnvironment) -> bool:
    """True when td is a whole number of samples (the sampled model exists)."""
    try:
        ve.delay_samples
    except UserError:
        return False
    return True
