"""Empirical transfer-function estimates of the closed-loop impedance Z = F/(jw X)
(paper sec. 4.2): ``force`` is the exogenous force, ``position`` the sampled position.

Estimators (``ESTIMATORS``):

* ``paper`` - the paper's method exactly: raw ratio of the DFTs of force and
  position over jw, smoothed in the complex domain by a Hamming window of
  ``window`` bins (normalised weights; the DC bin is left out, see docs/analysis.md).
* ``h1-welch`` - H1 = S_fx / S_ff from Welch-averaged spectra (Hann segments
  of 2^14 samples, 50 % overlap, linear detrend per segment; Bendat & Piersol,
  Random Data, sec. 9.1); Z = 1 / (jw H1).
* ``h1-log`` - H1 from the full-record DFT, cross and auto spectra averaged
  over bands of constant relative width (log-spaced resolution), on a log grid,
  less the band average's resolution bias (``_without_resolution_bias``).
* ``lpm`` - local polynomial method (Pintelon & Schoukens, System
  Identification, 2nd ed., sec. 7.2.2): in each band X_k = G(k) F_k + T(k) with
  G and the leakage/transient term T both quadratic in k, fitted by least
  squares. T absorbs the record-edge leakage that a drifting position (a pure
  damper lets the handle wander) throws over the low frequencies, so drift does
  not spoil the estimate. Log grid, constant relative band width.

Per frequency: coherence gamma^2, a 95 % radius |dZ| (``Z_err``), and a
low-coherence mask. Flags name the failure modes seen in the data.
"""
from __future__ import annotations

import functools
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy import fft, signal, special

from labbench.analysis.dataio import Recording, position_quantum
from labbench.analysis.progress import Progress, Steps
from labbench.model.effective import effective_impedances, measured_ws_star
from labbench.errors import UserError
from labbench.readout.verdict import BIAS_SE, DOUBTFUL, Verdict, judge

ESTIMATORS = ("lpm", "h1-log", "h1-welch", "paper")
DEFAULT_ESTIMATOR = "lpm"
GRID_PER_DECADE = 40
REL_BAND = 0.05  # half-width of a band relative to its centre frequency
# min 6 bins: the input-noise max error is half that of 4 (bench), resolution 0.37 rad/s on 2 min
MIN_HALF_BINS, MAX_HALF_BINS = 6, 100
LPM_ORDER = 2
LPM_GROUPS = (12, 40)  # half-width limits (bins) of the groups of bands fitted together
LPM_BIAS_SCREEN = 0.1  # a band is tested for bias when its estimated bias could exceed this x se
LPM_NARROWING = 4  # each Lepski step divides the half-width by this (4: two steps from 100 bins to 6)
CURVATURE_SIGNIFICANT = float(np.log(1e4))  # 1e-4 false alarms per band
# a fit's expectation of the paper estimate takes the model at PAPER_NODES runs of each
# window's bins, each run within PAPER_NODE_SPAN relative width (every bin at the low end)
PAPER_NODES, PAPER_NODE_SPAN = 16, 0.02
WELCH_SEGMENT = 2**14
HANN_INDEPENDENT = 3  # bins between uncorrelated Hann-tapered DFT coefficients
LOW_COHERENCE = 0.8
# near a sharp resonance Z changes by more than its own band from bin to bin and a local
# model's bias is not in the band: measured 20-28 % errors with 9-11 % bands at gamma^2
# 0.84-0.86 (issue 24); below this coherence such frequencies make the verdict doubtful
RESONANCE_COHERENCE = 0.9
W_BAND = (2.0, 100.0)  # rad/s, the band the accuracy targets speak of
# A possible bias of Z below this share of |Z| is no doubt (a tenth of the 1 % at which an
# impedance error starts to matter to a haptics lab): a noise-free simulator's bands are
# 1e-8 wide, and a 1e-10 curvature bias beyond them is not a result to distrust.
BIAS_MATTERS = 1e-3
# ... nor one below this many of its band's standard errors: the error it adds still lies
# inside the band's 1 - 1e-6 tail (|dZ| / se ~ 5.6 at 7 dof) unless the noise alone is beyond
# 2.6 se. Both bias estimates here are bounds (the local model's Taylor term, the coherence's
# bound on sensor noise), measured above the errors they bound; on the method-map grid no
# record with a bias below 3 se had an error beyond its band's tail (issue 30: at 0.5 se, the
# 0.9 coverage rule of BIAS_SE, 60 of 150 records within every band were called doubtful)
BIAS_FAR = 3.0
# The coherence's bound on force-sensor noise is no bound at an anti-resonance, where |Z| is
# small and noise dominates: there a 2.1 se bound stood beside a 9.6 se (79 %) error (issue
# 30's grid, a spring at 0.9 K_max under 0.05 N of sensor noise on 0.25 N). Sensor noise
# biases Z wherever it shows, so its doubt speaks from 2 standard errors (on the grid's sensor
# cells: 80 of 199 records within their bands doubtful, against 66 at 3 se with one silent
# failure; at any se below gamma^2 = 0.8: 114).
FORCE_NOISE_FAR = 2.0
LITTLE_EXCITATION = 1e-3  # force power relative to its in-band median
QUANT_SNR = 0.01  # quantisation noise power relative to position power
LEAKAGE = 0.1  # edge-leakage amplitude relative to |X| that counts as drift


@dataclass
class FitPoints:
    """What a model fitted to an estimate (``labbench.analysis.loopfit``) compares, at the
    frequencies ``w[idx]`` of the result: the estimate there, its standard error, and the
    estimator's expectation of it given a model of the truth."""

    idx: np.ndarray  # indices into EtfeResult.w
    Z_se: np.ndarray  # standard error of Z at them
    # (model: w -> Z, sel) -> the expected estimate at idx[sel] when the truth is model;
    # None: the model itself (an unbiased estimator with no smoothing the model must follow)
    expect: Callable | None = None


@dataclass
class EtfeResult:
    estimator: str
    w: np.ndarray  # rad/s
    Z: np.ndarray  # N s/m, complex
    coherence: np.ndarray
    Z_err: np.ndarray  # 95 % radius |dZ|
    Z_se: np.ndarray  # standard error sqrt(E |dZ|^2) (Z_err in these: ``radius95``)
    low_coherence: np.ndarray  # bool
    flags: list = field(default_factory=list)
    window: int | None = None
    force_power: np.ndarray | None = field(default=None, repr=False)  # mean |F_k|^2 near each w
    verdict: Verdict = field(default_factory=Verdict)
    # () -> complex correlation of the errors of G = 1 / (jw Z) between the frequencies
    # (neighbouring bands share DFT bins); None: the estimator does not know it
    error_corr: Callable[[], np.ndarray] | None = field(default=None, repr=False)
    # frequencies whose band may hold a bias it does not show (a local model that cannot
    # follow a sharp resonance even at the narrowest band); None: the estimator cannot tell
    unresolved: np.ndarray | None = field(default=None, repr=False)
    # relative upward bias of Z that force-sensor noise could cause, (1 - g^2) / g^2, per
    # frequency; 0 where the record's force is the command itself (``force_is_command``)
    eiv_bound: np.ndarray | None = field(default=None, repr=False)
    # lpm on a record whose force a sensor may have read (``_reach_force_reading``): the
    # reading with the noise in the force, and what the 95 % radius Z_err holds beyond its
    # noise's radius95(dof) * Z_se to reach it (N s/m per frequency); None: the force is the command
    Z_force: np.ndarray | None = field(default=None, repr=False)
    Z_allow: np.ndarray | None = field(default=None, repr=False)
    # (mask of usable frequencies) -> FitPoints; None: every usable frequency, Z_se, the model
    fit_points: Callable[[np.ndarray], FitPoints] | None = field(default=None, repr=False)
    # relative size of the local model's bias in its band, 3/35 |g2|^2 / |g0|^2 (``_lpm``)
    bias_rel: np.ndarray | None = field(default=None, repr=False)
    duration_s: float | None = None

    def as_dict(self) -> dict:
        eff = effective_impedances(self.w, self.Z)
        return {
            "estimator": self.estimator,
            "w": self.w,
            "Z_re": self.Z.real,
            "Z_im": self.Z.imag,
            "ES": eff.ES,
            "ED": eff.ED,
            "EM": eff.EM,
            "coherence": self.coherence,
            "ws_star": measured_ws_star(self.w, eff.ES),
            "wb_star": None,
            "Z_err": self.Z_err,
            "low_coherence": self.low_coherence,
            "flags": list(self.flags),
            "verdict": self.verdict.as_dict(),
        }


def etfe(rec: Recording, estimator: str | None = None, window: int = 200,
         band_rad_s: tuple[float, float] | None = None, progress: Progress | None = None,
         cancel: threading.Event | None = None) -> EtfeResult:
    """Estimate Z(jw) from a recording with the named estimator (default DEFAULT_ESTIMATOR);
    its verdict speaks of ``band_rad_s`` (``analysis_band``; None: ``W_BAND``).
    ``progress``, ``cancel``: ``labbench.analysis.progress`` (Cancelled once ``cancel`` is set)."""
    steps = Steps(progress, cancel)
    steps.report(0.0, "transforming")
    estimator = estimator or DEFAULT_ESTIMATOR
    if estimator not in ESTIMATORS:
        raise UserError(f"unknown estimator {estimator!r}; choose one of {', '.join(ESTIMATORS)}")
    if window < 3:
        raise UserError(f"--window must be at least 3 bins, got {window}")
    T = 1.0 / rec.fs
    f = np.asarray(rec.force, float)
    x = np.asarray(rec.position, float)
    for name, values in (("force", f), ("position", x)):
        if np.ptp(values) == 0:
            raise UserError(f"{rec.source}: {name} never changes: no frequency response to estimate")
    F = fft.rfft(f)
    steps.check()
    X = fft.rfft(x)
    dw = 2 * np.pi / (len(f) * T)
    steps.report(0.3, f"estimating ({estimator})")
    if estimator == "h1-welch":
        res = _h1_welch(f, x, rec.fs, steps.check)
    else:
        if estimator == "paper":
            res = _paper(F, X, dw, window)
        elif estimator == "h1-log":
            res = _h1_log(F, X, dw)
        else:
            res, other = _lpm(F, X, dw, reverse=not force_is_command(rec.meta))
            if other is not None:
                _reach_force_reading(res, other)
    coh = np.clip(res.coherence, 1e-12, 1.0)
    res.eiv_bound = np.zeros_like(coh) if force_is_command(rec.meta) else (1 - coh) / coh
    steps.report(0.9, "checking the estimate")
    res.duration_s = len(f) * T
    findings = _findings(res, rec, F, X)
    res.flags = [fd.flag for fd in findings if fd.flag]
    if res.w[0] > W_BAND[0]:
        res.flags.insert(0, _short_record(res, W_BAND[0]))
    res.verdict = _verdict(res, findings, band_rad_s)
    steps.report(1.0, "estimated")
    return res


def force_is_command(meta: dict) -> bool:
    """Whether the record's force is the command itself (``force_hold`` = zoh: a bench's
    held command, docs/analysis.md), so no sensor noise sits on it; else (a force sensor's
    reading, or unknown) noise on it biases every estimate of Z up by S_nn / S_ff
    (errors in the variables), at most (1 - g^2) / g^2 when all the incoherence is that noise."""
    return meta.get("force_hold") == "zoh"


# ----------------------------------------------------------------------------- estimators
def _paper(F, X, dw, window) -> EtfeResult:
    k = np.arange(1, len(F))  # DC left out: F/(jw X) is undefined there
    w = k * dw
    raw = F[k] / (1j * w * X[k])
    h = np.hamming(window)
    num = signal.oaconvolve(raw, h, mode="same")
    den = signal.oaconvolve(np.ones(len(raw)), h, mode="same")
    Z = num / den
    # coherence and spread from the same window: weighted agreement of the raw ratios
    Sff = signal.oaconvolve(np.abs(F[k]) ** 2, h, mode="same")
    Sxx = signal.oaconvolve(np.abs(X[k]) ** 2, h, mode="same")
    Sfx = signal.oaconvolve(np.conj(F[k]) * X[k], h, mode="same")
    coh = np.clip(np.abs(Sfx) ** 2 / (Sff * Sxx), 0, 1)
    n_eff = h.sum() ** 2 / np.sum(h**2)
    se, err = _h1_err(Z, coh, n_eff)
    return EtfeResult("paper", w, Z, coh, err, se, coh < LOW_COHERENCE, window=window,
                      fit_points=lambda use: _paper_fit_points(use, F, X, raw, Z, dw, h))


def _paper_fit_points(use, F, X, raw, Z, dw, h) -> FitPoints:
    """The paper estimate as a fit should read it (``FitPoints``).

    Its smoothing makes neighbouring bins share raw ratios, so a fit takes the centres of
    windows that do not overlap (at least the window apart, and GRID_PER_DECADE per decade
    at most): independent points, as many as the data resolve. Two things make the
    estimate differ from the truth Z where the model must follow them:

    * the window's average: E[Z_hat(k)] is the weighted mean of the expected raw ratios
      over the window (at the low end of a record they change by far more than the noise
      over a window: K / (jw) across 0.05-10 rad/s);
    * noise on the position: for X_j = G F_j + N_j, N_j circular Gaussian of power s^2,
      E[F_j / (jw X_j)] = Z (1 - exp(-|G F_j|^2 / s^2)) (the mean of the reciprocal of a
      noncentral complex Gaussian), which averages to gamma^2 Z over a random excitation:
      the raw ratio is biased low by the incoherent share (on a 2-min simulated record
      -16 % at gamma^2 0.8-0.9, -0.4 % above 0.99; the loop fit read that as a misfit,
      chi^2/dof 3.2e3). s^2 is what the model leaves of the position over the window,
      sum_j w_j |X_j - G F_j|^2 (leakage included: to the ratio it is noise like any other).

    The model is evaluated at the weighted mean frequency of each run of a window's bins
    (PAPER_NODES runs, each also within PAPER_NODE_SPAN relative width: at the record's low
    end every bin), the attenuation bin by bin with the known F_j. The standard error is
    the window's weights applied to the raw ratios' spread about the estimate,
    sqrt(sum_j w_j^2 |raw_j - Z_hat_j|^2).
    """
    L, n = len(h), len(raw)
    centres = _spaced(np.flatnonzero(use), L)
    # Z_hat[i] = sum_m h[m] raw[i + c - m] / (sum of h over bins that exist): oaconvolve "same"
    m = np.arange(L)
    j = centres[:, None] + (L - 1) // 2 - m[None, :]
    win, col = np.nonzero((j >= 0) & (j < n))  # flat: window, column (windows never overlap)
    j = j[win, col]
    wts = h[col] / np.bincount(win, h[col])[win]
    se = np.sqrt(np.bincount(win, wts**2 * np.abs(raw[j] - Z[j]) ** 2, len(centres)))
    bins = j + 1.0
    # runs: a new node where the uniform block or the relative-width block changes
    key = np.stack([win, m[col] * PAPER_NODES // L,
                    np.floor(np.log(bins) / np.log1p(PAPER_NODE_SPAN)).astype(int)], axis=1)
    _, node = np.unique(key, axis=0, return_inverse=True)
    node = node.ravel()
    wsum = np.bincount(node, wts)
    w_node = np.bincount(node, wts * bins) / np.where(wsum > 0, wsum, 1.0) * dw
    node_win = np.zeros(len(w_node), int)
    node_win[node] = win
    Fj, Xj = F[j + 1], X[j + 1]
    tiny = np.finfo(float).tiny

    def expect(model, sel=slice(None)):
        Gn = 1.0 / (1j * w_node * model(w_node))
        GF = Gn[node] * Fj
        # what the model leaves of the position is its noise
        s2 = np.bincount(win, wts * np.abs(Xj - GF) ** 2, len(centres))
        att = -np.expm1(-np.abs(GF) ** 2 / np.maximum(s2[win], tiny))
        per_node = np.bincount(node, wts * att, len(w_node))
        zn = per_node / (1j * w_node * Gn)
        return (np.bincount(node_win, zn.real, len(centres))
                + 1j * np.bincount(node_win, zn.imag, len(centres)))[sel]

    return FitPoints(centres, se, expect)


def _spaced_points(use, se, gap) -> FitPoints:
    idx = _spaced(np.flatnonzero(use), gap)
    return FitPoints(idx, se[idx])


def _spaced(idx: np.ndarray, gap: int) -> np.ndarray:
    """Increasing indices from ``idx``, each at least ``gap`` and a GRID_PER_DECADE step of the
    log grid after the one before (indices are bins - 1)."""
    out, step = [], 10 ** (1 / GRID_PER_DECADE)
    i = 0
    while i < len(idx):
        out.append(int(idx[i]))
        i = int(np.searchsorted(idx, max(idx[i] + gap, np.ceil((idx[i] + 1) * step) - 1)))
    return np.array(out, int)


def radius95(dof) -> np.ndarray:
    """95 % radius of a complex estimate in its standard errors when the error variance is
    itself estimated with ``dof`` complex degrees of freedom: |dZ|^2 / se^2 ~ F(2, 2 dof)
    (the complex form of Student's t: Goodman 1965, the confidence regions of frequency
    response functions). sqrt(ln 20) = 1.73 for dof -> infinity, 1.93 for dof = 7 (the
    narrowest LPM band), whose plug-in 1.73 covers 92 %."""
    dof = np.maximum(np.asarray(dof, float), 1.0)
    return np.sqrt(special.fdtri(2, 2 * dof, 0.95))


def _h1_err(Z, coh, n_avg):
    """(standard error, 95 % radius) of Z from H1 statistics over n averaged bins or
    segments: a one-parameter complex least-squares fit, so |dG|^2 / |G|^2 has the scale
    (1 - g^2) / (g^2 (n - 1)) and n - 1 degrees of freedom (Bendat & Piersol, Random Data,
    eq. 9.52 with the estimated noise's own dof; ``radius95``)."""
    n = np.maximum(np.asarray(n_avg, float), 2.0)
    rel = np.sqrt(np.maximum(1 - coh, 0) / (np.maximum(coh, 1e-12) * (n - 1)))
    se = np.abs(Z) * rel
    return se, radius95(n - 1) * se


def _h1_welch(f, x, fs, check=lambda: None) -> EtfeResult:
    nper = min(WELCH_SEGMENT, len(f))
    kw = {"fs": fs, "nperseg": nper, "detrend": "linear"}
    freq, Sff = signal.welch(f, **kw)
    check()  # each spectrum is a pass over the record
    _, Sxx = signal.welch(x, **kw)
    check()
    _, Sfx = signal.csd(f, x, **kw)
    k = slice(1, None)
    w = 2 * np.pi * freq[k]
    Z = Sff[k] / (1j * w * Sfx[k])
    coh = np.clip(np.abs(Sfx[k]) ** 2 / (Sff[k] * Sxx[k]), 0, 1)
    n_seg = max(1, 2 * len(f) // nper - 1)
    se, err = _h1_err(Z, coh, n_seg)
    # a fit takes bins HANN_INDEPENDENT apart (Hann-tapered DFT coefficients of white noise
    # correlate -2/3 at one bin, 1/6 at two, 0 at three), at most GRID_PER_DECADE per decade
    return EtfeResult("h1-welch", w, Z, coh, err, se, coh < LOW_COHERENCE,
                      fit_points=lambda use: _spaced_points(use, se, HANN_INDEPENDENT))


@functools.lru_cache(maxsize=8)
def _grid(n_bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Log-spaced centre bins (GRID_PER_DECADE per decade) and their band half-widths."""
    k_lo = MIN_HALF_BINS + 1
    k_hi = n_bins - 1 - MAX_HALF_BINS
    if k_hi <= k_lo:
        raise UserError("record too short for a frequency response (need a few hundred samples)")
    n = int(np.ceil(np.log10(k_hi / k_lo) * GRID_PER_DECADE)) + 1
    k = np.unique(np.round(np.geomspace(k_lo, k_hi, n)).astype(int))
    half = np.clip(np.round(REL_BAND * k).astype(int), MIN_HALF_BINS, MAX_HALF_BINS)
    half = np.minimum(half, k - 1)
    return k, half


def _band_sum(values, k, half):
    c = np.concatenate([[0], np.cumsum(values)])
    return c[k + half + 1] - c[k - half]


def _h1_log(F, X, dw) -> EtfeResult:
    k, half = _grid(len(F))
    w = k * dw
    Sff = _band_sum(np.abs(F) ** 2, k, half)
    Sxx = _band_sum(np.abs(X) ** 2, k, half)
    Sfx = _band_sum(np.conj(F) * X, k, half)
    coh = np.clip(np.abs(Sfx) ** 2 / (Sff * Sxx), 0, 1)
    G, inflation = _without_resolution_bias(Sfx / Sff, w, half, dw)
    Z = 1.0 / (1j * w * G)
    se, err = _h1_err(Z, coh, 2 * half + 1)
    return EtfeResult("h1-log", w, Z, coh, err * inflation, se * inflation, coh < LOW_COHERENCE,
                      force_power=Sff / (2 * half + 1))


def _without_resolution_bias(G, w, half, dw) -> tuple[np.ndarray, np.ndarray]:
    """G averaged over bands of 2 half + 1 bins, less the average's bias, and the factor on
    its standard error that the correction costs.

    A band average reads E[G_hat] = G + G'' dw^2 half (half + 1) / 6 (the bins' mean squared
    offset; Bendat & Piersol, Random Data, sec. 8.5.4: resolution bias B_e^2 G'' / 24). Near
    the closed loop's anti-resonance that was 0.5 standard errors on 2-min records (1.3 % of
    |Z| at 20-60 rad/s, 4-6 sigma over 60 records) and made h1-log's one error beyond its
    band on the method-map grid. G'' is read from the estimate itself as a second difference
    over one band width either side (interpolated on the grid; no correction where that
    leaves the grid); its noise, c^2 of the neighbours' variances with c ~ 1/24, and the
    centre's share (1 + 2 c) give the factor sqrt((1 + 2 c)^2 + 2 c^2) ~ 1.09."""
    d = (2 * half + 1) * dw
    inside = (w - d >= w[0]) & (w + d <= w[-1])

    def at(x):
        return np.interp(x, w, G.real) + 1j * np.interp(x, w, G.imag)

    c = np.where(inside, half * (half + 1) / (6.0 * (2 * half + 1) ** 2), 0.0)
    return G - c * (at(w - d) - 2 * G + at(w + d)), np.sqrt((1 + 2 * c) ** 2 + 2 * c**2)


def _lpm(F, X, dw, reverse: bool = False) -> tuple[EtfeResult, EtfeResult | None]:
    """The local polynomial method's fit of X = G F + T, Z = 1 / (jw G); with ``reverse``
    also the same fit of F = (jw Z) X + T (``_reach_force_reading``), from the same moments
    and batches (the moments, the costly part, are gathered once)."""
    k, half = _grid(len(F))
    w = k * dw
    pairs = [(F, X), (X, F)][:1 + reverse]
    mom, n_in = _lpm_moments(F, X, k, half)
    fits = _lpm_solve(np.concatenate([mom, _swapped(mom)][:len(pairs)]), np.tile(n_in, len(pairs)),
                      len(pairs))
    halves = [half.copy() for _ in pairs]  # narrowed below; the grid is cached
    # Where the band is wider than G is smooth (a sharp resonance: a quadratic cannot follow
    # a peak a few bins wide), the local model's bias is not in its band. Test such a band
    # against the same fit over a narrower band (LPM_NARROWING; Lepski's method, Goldenshluger
    # & Nemirovski 1997): the nested estimates differ by noise of variance se_narrow^2 -
    # se_wide^2 when both are unbiased; a larger difference (95 %) means the wide band is
    # biased, so the narrow one replaces it and is tested the same way, down to
    # MIN_HALF_BINS. Only bands whose own quadratic term says the bias could matter are
    # tested (the cost of a second pass): near a pole the Taylor terms of G grow
    # geometrically, |g4| ~ |g2|^2 / |g0|, and a quadratic fit leaves about 3/35 of the
    # quartic term in g0 (Legendre projection of r^4).
    plans = [_narrowing_steps(fit, half) for fit in fits]
    sizes = [sum(len(b) for b, _ in steps) for steps in plans]
    if sum(sizes):  # every step of every direction fitted in one batch (cheaper)
        mom, n_in = _lpm_moments(F, X, np.concatenate([k[b] for steps in plans for b, _ in steps]),
                                 np.concatenate([h for steps in plans for _, h in steps]))
        if reverse:
            mom[sizes[0]:] = _swapped(mom[sizes[0]:])
        cand = _lpm_solve(mom, n_in)[0]
        start = 0
        for fit, h, steps in zip(fits, halves, plans):
            start = _narrow(fit, h, steps, cand, start)
    out = [_lpm_result(fit, h, k, w, *pair) for fit, h, pair in zip(fits, halves, pairs)]
    return out[0], (out[1] if reverse else None)


def _narrowing_steps(fit, half) -> list[tuple[np.ndarray, np.ndarray]]:
    """Lepski's steps for the bands ``_may_be_biased`` screens in: (bands, narrower
    half-widths) per step, each step the bands still wider than MIN_HALF_BINS."""
    todo = np.flatnonzero((half > MIN_HALF_BINS) & _may_be_biased(fit, LPM_BIAS_SCREEN))
    steps = []
    bands, h = todo, half[todo]
    while bands.size:
        h = np.maximum(h // LPM_NARROWING, MIN_HALF_BINS)
        steps.append((bands, h))
        bands, h = bands[h > MIN_HALF_BINS], h[h > MIN_HALF_BINS]
    return steps


def _narrow(fit, half, steps, cand, start: int) -> int:
    """Replace each band of ``fit`` (and ``half``) its narrower fit shows biased, step by step
    (``_lpm``): ``cand`` holds the steps' fits from index ``start``; returns where they end."""
    live = np.zeros(len(half), bool)  # still narrowing: every step so far found a bias
    if steps:
        live[steps[0][0]] = True
    for bands, h in steps:
        part = [c[start:start + len(bands)] for c in cand]
        start += len(bands)
        spread = np.sqrt(np.maximum(part[1] ** 2 - fit[1][bands] ** 2, 0.0))
        biased = live[bands] & (np.abs(part[0] - fit[0][bands]) > radius95(part[4]) * spread)
        for mine, theirs in zip(fit, part):
            mine[bands[biased]] = theirs[biased]
        half[bands[biased]] = h[biased]
        live[bands[~biased]] = False
    return start


def _lpm_result(fit, half, k, w, F, X) -> EtfeResult:
    """lpm's estimate of Z = 1 / (jw G) from the fits of X = G F + T (``_lpm_solve``)."""
    G, sG, s2, Pf, dof = fit[:5]
    # at the narrowest band a sharp resonance can still bend G more than a quadratic follows
    unresolved = (half == MIN_HALF_BINS) & _may_be_biased(fit, BIAS_SE) & _curved(fit)
    Z = 1.0 / (1j * w * G)
    # coherence: share of the output (transient removed) that G F explains
    explained = np.abs(G) ** 2 * Pf
    coh = np.clip(explained / (explained + s2), 0, 1)
    se = np.abs(Z) * sG / np.abs(G)  # first order: |dZ| / |Z| = |dG| / |G|
    return EtfeResult("lpm", w, Z, coh, radius95(dof) * se, se, coh < LOW_COHERENCE, force_power=Pf,
                      error_corr=lambda: _lpm_correlation(F, X, k, half), unresolved=unresolved,
                      bias_rel=3 / 35 * fit[5] / np.abs(G) ** 2)


def _reach_force_reading(res: EtfeResult, other: EtfeResult) -> None:
    """Widen lpm's bands to reach the reading that puts the noise in the force.

    lpm fits X = G F + T: noise on the motion is its output noise, noise a force sensor adds
    is in its regressor and biases |Z| up by S_nn / S_ff (errors in the variables). The same
    local fit of F = (jw Z) X + T (``other``, ``_lpm``'s reverse) has the opposite case:
    unbiased under force noise, biased by motion noise. With noise on both, |Z| lies between
    the two readings (H1 and H2 of Bendat & Piersol, Random Data, sec. 9.2.4), so each band
    (``Z_err``) grows to reach the other reading's band; ``Z_force`` keeps that reading,
    ``Z_allow`` the growth. The second fit also follows a sharp resonance of the display
    where the first cannot: there the impedance is smooth and the admittance a peak a few
    bins wide (springs at 0.75 and 0.9 K_max, 30 s, sensor noise: lpm's errors reached
    137 % of |Z|, the force reading's 27 %; on issue 30's grid the bands held all 93
    frequencies where the coherence's bound on the noise exceeded two standard errors, 61
    before)."""
    with np.errstate(divide="ignore", invalid="ignore"):  # other's "Z" is 1 / (jw Y), Y = jw Z
        res.Z_force = -1.0 / (other.w ** 2 * other.Z)
        reach = np.abs(res.Z - res.Z_force) + np.abs(res.Z_force) * other.Z_err / np.abs(other.Z)
        res.Z_allow = np.where(np.isfinite(reach), np.maximum(reach - res.Z_err, 0.0), 0.0)
    res.Z_err = res.Z_err + res.Z_allow


def _may_be_biased(fit, share: float) -> np.ndarray:
    """Bands whose estimated local-model bias, 3/35 |g2|^2 / |g0| (``_lpm``), exceeds ``share``
    of G's standard error."""
    G, sG, curv2 = fit[0], fit[1], fit[5]
    return 3 / 35 * curv2 / np.abs(G) > share * sG


def _curved(fit) -> np.ndarray:
    """Bands whose quadratic term is real, not noise: |g2|^2 beyond CURVATURE_SIGNIFICANT times
    its noise variance (exceeded by a circular complex noise with probability e^-x)."""
    return fit[5] > CURVATURE_SIGNIFICANT * fit[6]


def _lpm_correlation(F, X, k, half) -> np.ndarray:
    """Correlation of the errors of the local estimates G_i = sum_j a_ij X_j (``_lpm_weights``'s
    weights a): E[dG_i conj(dG_l)] = s^2 sum_j a_ij conj(a_lj) for DFT bins j carrying
    independent noise of a common local variance s^2, normalised to 1 on the diagonal."""
    from scipy import sparse

    rows, cols, vals = [], [], []
    group = np.searchsorted(LPM_GROUPS, half)
    for g in np.unique(group):
        sel = np.flatnonzero(group == g)
        a, idx = _lpm_weights(F, X, k[sel], half[sel])
        inside = a != 0
        rows.append(np.broadcast_to(sel[:, None], a.shape)[inside])
        cols.append(idx[inside])
        vals.append(a[inside])
    A = sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(len(k), len(F)))
    C = (A @ A.conj().T).toarray()
    d = np.sqrt(np.real(np.diag(C)))
    return C / np.outer(d, d)


def _lpm_weights(F, X, k, half) -> tuple[np.ndarray, np.ndarray]:
    """The local fits' G as weights of the bins (a, bins): G = sum_j a[:, j] X[bins[:, j]],
    a = conj(F_j) P1(r_j) + P2(r_j) from e0' M^-1 Phi^H (a is 0 outside each band)."""
    q = LPM_ORDER + 1
    offs, inside, idx, mom, Fw = _lpm_window(F, X, k, half)
    Minv = np.linalg.inv(_lpm_normal(mom)[0])
    r = np.where(inside, offs[None, :] / half[:, None], 0.0)
    rp = r[:, :, None] ** np.arange(q)
    P1 = np.einsum("gjp,gp->gj", rp, Minv[:, 0, :q])
    P2 = np.einsum("gjp,gp->gj", rp, Minv[:, 0, q:])
    return np.where(inside, np.conj(Fw) * P1 + P2, 0), idx


def _lpm_moments(F, X, k, half) -> tuple[np.ndarray, np.ndarray]:
    """The weighted moments of ``_lpm_window`` for bands of any widths (band, row, power),
    and each band's number of bins: bands of similar width are gathered together, so narrow
    ones are not padded to the widest."""
    group = np.searchsorted(LPM_GROUPS, half)
    mom = np.empty((len(k), 9, 2 * LPM_ORDER + 1))
    for g in np.unique(group):
        sel = group == g
        mom[sel] = _lpm_window(F, X, k[sel], half[sel])[3]
    return mom, 2 * half + 1


def _lpm_window(F, X, k, half):
    """Bands centred on bins k with half-widths half, padded to the widest: the offsets, the
    mask of bins inside each band, the bins, and the weighted moments sum_j w_j r_j^p of the
    normal equations of X_j = sum_p g_p r^p F_j + sum_p t_p r^p (r = offset / half; weights
    zero outside the band) for the weights |F|^2, F, 1, conj(F) X, X (complex ones split)
    and |X|^2: r^p = offset^p / half^p, so one real matmul with offset^p serves all."""
    H = int(half.max())
    offs = np.arange(-H, H + 1)
    inside = np.abs(offs)[None, :] <= half[:, None]
    idx = np.clip(k[:, None] + offs[None, :], 0, len(F) - 1)
    Fw = np.where(inside, F[idx], 0)
    Xw = np.where(inside, X[idx], 0)
    FX = np.conj(Fw) * Xw
    W = np.stack([np.abs(Fw) ** 2, Fw.real, Fw.imag, inside, FX.real, FX.imag, Xw.real, Xw.imag,
                  np.abs(Xw) ** 2], axis=1)
    powers = np.arange(2 * LPM_ORDER + 1)
    mom = (W.reshape(-1, len(offs)) @ (offs[:, None].astype(float) ** powers)).reshape(len(k), 9, -1)
    mom /= half[:, None, None].astype(float) ** powers
    return offs, inside, idx, mom, Fw


def _swapped(mom: np.ndarray) -> np.ndarray:
    """The moments of the fit with F and X swapped (F = G' X + T): the same sums in another
    order, conj(X) F being conj(conj(F) X)."""
    out = mom[:, [8, 6, 7, 3, 4, 5, 1, 2, 0]]
    out[:, 5] *= -1
    return out


def _lpm_normal(mom: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The normal equations' matrix M and right-hand side of the local fits (``_lpm_window``):
    parameters (g_0..g_q-1, t_0..t_q-1), Hankel in the moments' powers."""
    q = LPM_ORDER + 1
    hank = np.add.outer(np.arange(q), np.arange(q))  # p + p'
    mom_f = mom[:, 1] + 1j * mom[:, 2]
    M = np.empty((len(mom), 2 * q, 2 * q), complex)
    M[:, :q, :q] = mom[:, 0][:, hank]
    M[:, :q, q:] = np.conj(mom_f[:, hank])
    M[:, q:, :q] = mom_f[:, hank]
    M[:, q:, q:] = mom[:, 3][:, hank]
    rhs = np.concatenate([mom[:, 4, :q] + 1j * mom[:, 5, :q], mom[:, 6, :q] + 1j * mom[:, 7, :q]], axis=1)
    return M, rhs


def _lpm_solve(mom: np.ndarray, n_in: np.ndarray, parts: int = 1) -> list[tuple]:
    """The local fits from their moments (``_lpm_moments``), in ``parts`` equal parts.

    Returns per part G, its standard error, the residual variance per bin, the mean |F|^2,
    the residual's degrees of freedom (bins less the 2 (LPM_ORDER + 1) complex parameters)
    and |g2|^2, the squared size of G's quadratic term over the band, and its noise variance.
    """
    q = LPM_ORDER + 1
    M, rhs = _lpm_normal(mom)
    Minv = np.linalg.inv(M)
    theta = np.einsum("gab,gb->ga", Minv, rhs)
    rss = mom[:, 8, 0] - np.real(np.einsum("ga,ga->g", np.conj(theta), rhs))
    dof = np.maximum(n_in - 2 * q, 1)
    s2 = np.maximum(rss, 0) / dof
    var_g = s2 * np.real(Minv[:, 0, 0])
    # a negative variance is round-off of a near-singular band (nothing excited): no bound
    sG = np.where(var_g >= 0, np.sqrt(np.abs(var_g)), np.inf)
    fit = (theta[:, 0], sG, s2, mom[:, 0, 0] / n_in, dof, np.abs(theta[:, 2]) ** 2,
           s2 * np.abs(np.real(Minv[:, 2, 2])))
    n = len(mom) // parts
    return [tuple(a[i * n:(i + 1) * n] for a in fit) for i in range(parts)]


@dataclass(frozen=True)
class Finding:
    """One failure mode seen in the data: where it bites (``mask`` over ``EtfeResult.w``),
    whether the band there may miss the truth (``bias``: a doubt inside the band asked
    about) or is only wide (a limit, said in the verdict's notes), its ``flag`` (the
    sentence of ``EtfeResult.flags``; None: a judgement of the verdict's, not a property of
    the record, or a bias only outside W_BAND) and a short ``limit`` phrase for the notes."""

    name: str
    mask: np.ndarray
    bias: bool
    flag: str | None
    limit: str
    advice: str = ""  # what would settle a doubt


def _findings(res: EtfeResult, rec: Recording, F: np.ndarray, X: np.ndarray) -> list[Finding]:
    """Failure modes, each with the frequencies (rad/s) where it bites, over the whole grid:
    the verdict (``_verdict``) decides what they mean for the band asked about."""
    out = []
    n = len(rec.force)
    dw = 2 * np.pi * rec.fs / n
    w = res.w
    low = res.low_coherence
    if low.any():
        out.append(Finding("low-coherence", low, False,
                           f"low-coherence: {int(low.sum())} of {len(w)} frequencies have gamma^2 < "
                           f"{LOW_COHERENCE:g} ({_spans(w, low)} rad/s)",
                           f"coherence below {LOW_COHERENCE:g}, bands wide"))
    # force power per bin around each output frequency, against its median over W_BAND
    Pf = res.force_power if res.force_power is not None else _smooth_at(np.abs(F) ** 2, w, dw)
    band = (w >= W_BAND[0]) & (w <= W_BAND[1])
    ref = np.median(Pf[band]) if band.any() else np.median(Pf)
    weak = Pf < LITTLE_EXCITATION * ref
    if weak.any():
        out.append(Finding("little-excitation", weak, True,
                           f"little-excitation: force power below {100 * LITTLE_EXCITATION:g} % of its "
                           f"median at {_spans(w, weak)} rad/s; Z there is unreliable",
                           "too little force to measure Z"))
    q = position_quantum(np.asarray(rec.position))
    if q or res.estimator != "lpm":
        Px = _smooth_at(np.abs(_without_edge_jump(X, rec.position)) ** 2, w, dw)
    if q:
        noisy = n * q**2 / 12 > QUANT_SNR * Px
        if noisy.any():
            out.append(Finding("quantised-position", noisy, False,
                               f"quantised-position: encoder step {q:.3g} m; its noise exceeds "
                               f"{100 * QUANT_SNR:g} % of the position power at {_spans(w, noisy)} rad/s",
                               f"the encoder's quantisation ({q:.3g} m) dominates, bands wide"))
    if res.estimator != "lpm":
        # record-edge leakage: the jump x[-1] - x[0] of the periodic extension adds
        # about |jump| / (w T) to every |X_k| (lpm fits and removes this term)
        jump = abs(float(rec.position[-1] - rec.position[0]))
        leak = jump * rec.fs / w / np.maximum(np.sqrt(Px), 1e-300)
        leaky = leak > LEAKAGE
        if leaky.any():
            flag = (leaky & band).any() and (
                f"drift: position ends {jump:.3g} m from where it started; leakage exceeds "
                f"{100 * LEAKAGE:g} % of |X| at {_spans(w, leaky & band)} rad/s for this estimator "
                "(lpm removes it)") or None
            biased = leaky & _leak_biases(res.estimator, leak)
            for mask, bias in ((biased, True), (leaky & ~biased, False)):
                if mask.any():
                    out.append(Finding("drift", mask, bias, flag, "record-edge leakage of the drift",
                                       "use the lpm estimator, which removes it"))
                    flag = None  # one flag for both parts
    if res.eiv_bound is not None:
        biased = (res.eiv_bound * np.abs(res.Z) > FORCE_NOISE_FAR * res.Z_se) & (res.eiv_bound > BIAS_MATTERS)
        if biased.any():
            held = res.Z_allow is not None  # lpm's bands reach the force reading
            limit = ("band widened to hold the reading that puts the noise in the force" if held else
                     f"the coherence allows force-sensor noise that would bias |Z| up by as much as "
                     f"{100 * float(np.max(res.eiv_bound[biased])):.2g} %, beyond the band")
            out.append(Finding("force-noise", biased, not held, None, limit,
                               "state force_hold = zoh if the recorded force is the command (no sensor)"))
    sharp, how = _sharp(res)
    if sharp.any():
        out.append(Finding("narrow-band", sharp, True, None, f"{how}: the band may not hold the truth",
                           "a longer record narrows the bins"))
    return out


def _leak_biases(estimator: str, leak: np.ndarray) -> np.ndarray:
    """Where record-edge leakage (``leak``: its size relative to |X|) biases Z rather than
    widening its band. The paper's ratio of DFTs takes it in the denominator: a bias wherever
    it shows. H1 averages F conj(X) over bins, and leakage uncorrelated with the force only
    lowers the coherence, until it outgrows the signal itself (a drifting damper: 1.3-3.2 x |X|,
    where the bands stop holding: issue 24's grid). Welch detrends each segment."""
    if estimator == "paper":
        return np.ones(len(leak), bool)
    if estimator == "h1-log":
        return leak > 1.0
    return np.zeros(len(leak), bool)


def _short_record(res: EtfeResult, lo: float) -> str:
    return (f"short-record: {res.duration_s:.3g} s resolves only from {res.w[0]:.3g} rad/s; "
            f"{lo:g} rad/s needs about {_needed_s(res, lo):.0f} s")


def _needed_s(res: EtfeResult, lo: float) -> float:
    """Record length that resolves ``lo`` rad/s (the lowest frequency scales as 1 / length)."""
    return res.duration_s * res.w[0] / max(lo, 1e-12)


def _sharp(res: EtfeResult) -> tuple[np.ndarray, str]:
    """Frequencies where the band may not hold a local model's bias, and how it shows: the
    estimator's own bias estimate where it has one (lpm), beyond ``BIAS_MATTERS`` of |Z| and
    ``BIAS_FAR`` standard errors; else Z moving by more than its band from bin to bin at low
    coherence."""
    if res.unresolved is not None:
        bias = res.bias_rel if res.bias_rel is not None else np.full(len(res.w), np.inf)
        rel_se = res.Z_se / np.maximum(np.abs(res.Z), 1e-300)
        return res.unresolved & (bias > np.maximum(BIAS_MATTERS, BIAS_FAR * rel_se)), (
            "G bends more than the local model follows even at its narrowest band (a sharp "
            "resonance, or the lowest bins of a short record)")
    Z = res.Z
    step = np.abs(np.gradient(Z)) / np.maximum(np.abs(Z), 1e-300) if len(res.w) >= 3 else np.zeros(len(res.w))
    sharp = (res.coherence < RESONANCE_COHERENCE) & (step > res.Z_err / np.maximum(np.abs(Z), 1e-300))
    return sharp, (f"Z changes by more than its 95 % band between neighbouring frequencies and "
                   f"gamma^2 < {RESONANCE_COHERENCE:g} (a sharp resonance)")


def analysis_band(asked, w: np.ndarray) -> tuple[float, float]:
    """The band a verdict speaks of: ``asked`` (rad/s; None: ``W_BAND``, the accuracy
    targets' band) within the frequencies the record resolves (``w``)."""
    lo, hi = W_BAND if asked is None else asked
    if not (0 <= lo < hi):
        raise UserError(f"analysis band {lo:g}-{hi:g} rad/s: give 0 <= low < high")
    return max(float(lo), float(w[0])), min(float(hi), float(w[-1]))


def _verdict(res: EtfeResult, findings: list[Finding], asked) -> Verdict:
    """The verdict over the band asked about (``analysis_band``): doubtful where a bias
    finding bites inside it (its own words, its frequencies there); a limit inside it (low
    coherence, quantisation: the bands are wide, they still hold the truth) and anything
    outside it go to the notes. An ok verdict states the widest band around the asked one
    that no finding touches ("ok over 0.4-225 rad/s"). Nothing here makes Z failed: each
    frequency carries its own band."""
    w = res.w
    lo, hi = analysis_band(asked, w)
    notes = []
    if res.estimator == "paper":  # its bands come from the smoothing window's spread alone
        return judge([(DOUBTFUL, "the paper's estimator: its bands are not calibrated (they hold "
                                 "the truth at 57 % of the frequencies of the method map, 5 % on a "
                                 "drifting damper); use lpm for bands to trust")], (lo, hi))
    asked_lo = W_BAND[0] if asked is None else asked[0]
    if w[0] > asked_lo:
        notes.append(f"below {w[0]:.3g} rad/s not resolved: a {res.duration_s:.3g} s record; "
                     f"{asked_lo:g} rad/s needs about {_needed_s(res, asked_lo):.0f} s")
    if not lo < hi:
        return judge([(DOUBTFUL, f"the record resolves nothing of the band asked about "
                                 f"({asked_lo:g}-{W_BAND[1] if asked is None else asked[1]:g} rad/s)")],
                     None, notes)
    inside = (w >= lo) & (w <= hi)
    reasons = []
    for f in findings:
        here = f.mask & inside
        if here.any() and f.bias:
            reasons.append((DOUBTFUL, f"{f.name}: at {_spans(w, here)} rad/s {f.limit}"
                                      + (f"; {f.advice}" if f.advice else "")))
        elif here.any():
            notes.append(f"{f.limit} at {_spans(w, here)} rad/s")
        if (f.mask & ~inside).any():
            notes.append(f"outside the band: {f.limit} at {_spans(w, f.mask & ~inside)} rad/s")
    level_band = (lo, hi)
    if not reasons:
        level_band = _clean_extent(w, inside, [f.mask for f in findings])
    return judge(reasons, level_band, notes)


def _clean_extent(w: np.ndarray, inside: np.ndarray, masks) -> tuple[float, float]:
    """The widest run of frequencies around the ``inside`` ones that no mask touches."""
    touched = np.zeros(len(w), bool)
    for m in masks:
        touched |= m
    idx = np.flatnonzero(inside)
    a, b = idx[0], idx[-1]
    if touched[a:b + 1].any():
        return float(w[a]), float(w[b])
    while a > 0 and not touched[a - 1]:
        a -= 1
    while b < len(w) - 1 and not touched[b + 1]:
        b += 1
    return float(w[a]), float(w[b])


def _smooth_at(power: np.ndarray, w: np.ndarray, dw: float) -> np.ndarray:
    """Mean of a per-bin power over a band of relative half-width REL_BAND around each w."""
    k = np.clip(np.round(w / dw).astype(int), 1, len(power) - 2)
    half = np.clip(np.round(REL_BAND * k).astype(int), 1, k)
    half = np.minimum(half, len(power) - 1 - k)
    return _band_sum(power, k, half) / (2 * half + 1)


def _without_edge_jump(X: np.ndarray, x) -> np.ndarray:
    """DFT of x minus the ramp from x[0] to x[-1]: no edge-jump leakage.

    The ramp's DFT is known in closed form: sum_n n e^{-j 2 pi k n / N} = -N / (1 - e^{-j 2 pi k / N}).
    """
    N = len(x)
    jump = float(x[-1] - x[0])
    k = np.arange(1, len(X))
    ramp = -jump / (N - 1) * N / (-np.expm1(-2j * np.pi * k / N))
    out = X.copy()
    out[1:] -= ramp
    out[0] -= jump * N / 2
    return out


def _spans(w: np.ndarray, mask: np.ndarray, max_spans: int = 4) -> str:
    """Compact text of the runs of consecutive True in mask, as w ranges."""
    m = np.concatenate([[False], mask, [False]]).astype(int)
    starts = np.flatnonzero(np.diff(m) == 1)
    ends = np.flatnonzero(np.diff(m) == -1) - 1
    parts = [f"{w[a]:.3g}" if a == b else f"{w[a]:.3g}-{w[b]:.3g}" for a, b in zip(starts, ends)]
    more = f" and {len(parts) - max_spans} more" if len(parts) > max_spans else ""
    return ", ".join(parts[:max_spans]) + more
