"""Identify the device: f = m x'' + b x' [+ Fc sign(x')] [+ f0] (paper sec. 4.1,
eqs. 10-11 with x' and x'' put back where the physics has them).

Pipeline: derivatives of position by zero-phase filtered central differences
(``derivatives``); when the force has power beyond the derivative cut-off
(white noise, closed-loop trajectories) it goes through the same zero-phase
filter, which commutes with the linear terms; the force of a zero-order-hold
record is averaged over the two hold intervals around each sample, which makes
the second difference of a ZOH-driven mass exact; then l2 (least squares) or
l1 (exact LAD, ``l1``; with ``solver="cvxpy"`` every fit, jackknife
replicates included, goes through cvxpy, which is slow by design).

The Coulomb regressor is the low-passed sign of the velocity, L sign(x'):
the derivatives are those of the low-passed position, and L commutes with the
whole model, so m L x'' + b L x' + Fc L sign(x') = L f holds exactly where
f = m x'' + b x' + Fc sign(x') does (a raw sign against filtered derivatives
biases Fc low by ~10 % and b high). On a quantised encoder the sign is the
expected one given the velocity noise q / sqrt(12) x the filter's noise gain,
erf(x' / (sqrt(2) s_v)), so a velocity sign flipped by encoder noise near rest
is not taken for friction.

How the force reached the plant (``force_hold``): "zoh" (held over each
sample interval, as a bench command is) or "sample" (force and position
sampled at the same instants, e.g. a force sensor). Given, or from the
metadata, or, when neither says, chosen by the data: both readings are fitted
with the largest identifiable model and the lower blocked cross-validated loss
wins (forces low-passed alike for this comparison, so the two-sample mean of
the ZOH reading does not win by halving white noise); the result says which and by how much.

Model selection (``model="auto"``): blocked 5-fold cross-validation (folds are
interleaved contiguous blocks, so correlated neighbours do not leak between
training and test). A larger model replaces a smaller one only if

* its CV loss (the method's own: squared or absolute residual) is lower, fold by
  fold, by a log-ratio above two standard errors of the fold log-ratios and
  above 0.5 %, and by more than a floor set by the force ((0.1 % of the force
  rms)^2 for l2, 0.1 % of the mean |force| for l1);
* the new term is physically significant: its force |Fc| or |f0| is at least
  0.5 % of the force rms and 10 % of the larger model's residual rms (exact or
  very long records "support" a millinewton term that only soaks up
  discretisation error).

``selection["steps"]`` records every test and ``selection["reason"]`` says why
the model was chosen.

95 % intervals: delete-one-block jackknife over 10 contiguous blocks (robust
to the strong serial correlation of filtered residuals; Kunsch 1989),
theta +- t(0.975, 9) * SE_jack.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage, special, stats

from labbench.analysis import l1
from labbench.analysis.dataio import Recording, position_quantum
from labbench.analysis.derivatives import (
    CUTOFF_FACTOR,
    default_cutoff,
    differentiate,
    force_band,
    lowpass,
)
from labbench.errors import UserError
from labbench.verdict import DOUBTFUL, FAILED, Verdict, judge

MODELS = ("mb", "mbc", "mbco")
MODEL_CHOICES = MODELS + ("auto",)
METHODS = ("l2", "l1")
SOLVERS = ("fast", "cvxpy")
TERMS = {"mb": ("m", "b"), "mbc": ("m", "b", "coulomb"), "mbco": ("m", "b", "coulomb", "offset")}
CV_FOLDS, CV_BLOCKS = 5, 20
JACKKNIFE_BLOCKS = 10
MIN_GAIN_SE, MIN_GAIN_REL, MIN_GAIN_FORCE = 2.0, 0.005, 1e-3
# physical significance of a Coulomb or offset term: |term| against the force rms and
# against the larger model's residual rms
TERM_VS_FORCE, TERM_VS_RESIDUAL = 0.005, 0.1
HOLDS = ("zoh", "sample")
# the wrong force timing costs 100x and more in CV loss where it matters (a fast continuous
# chirp, tests/test_identify.py); a ratio of 1.0068 decides nothing (issue 24)
HOLD_MIN_GAIN = 0.02
SHORT_RECORD = 2000  # samples used
WIDE_CI_REL = 0.10  # half-width of the m or b interval, relative
OUTLIER_SIGMAS, OUTLIER_BLOCK = 8.0, 256
QUANT_NOISE_REL = 0.02  # encoder noise in x'' relative to the x'' signal
# stick-slip: at rest = |x'| below REST_SIGMAS x the encoder's velocity noise (or
# REST_REL x the velocity std on unquantised data); pushed = |f| above STICK_FORCE_REL
# x the force rms. Clean mass-dampers (chirp reversals) give <= 1 % such samples.
REST_SIGMAS, REST_REL, STICK_FORCE_REL, STICK_FRACTION = 4.0, 1e-3, 0.01, 0.05
# a delay between force and motion that the model lacks leaves m tau x''' in the residual
# (f(t) = m x''(t + tau) + b x'(t + tau) ~ m x'' + b x' + m tau x'''): judged doubtful when
# |tau| exceeds DELAY_SAMPLES samples and x''' explains DELAY_EXPLAINS of the residual variance
DELAY_SAMPLES, DELAY_EXPLAINS = 0.25, 0.2
UNDECIDED_SE = 1.0  # a model step within this many SE of the MIN_GAIN_SE threshold is undecided


@dataclass
class IdResult:
    model: str
    method: str
    params: dict  # m, b, coulomb, offset (absent terms: None)
    ci95: dict  # name -> (lo, hi)
    rms_residual: float
    n_used: int
    explained: float
    cutoff_hz: float
    flags: list = field(default_factory=list)
    selection: dict = field(default_factory=dict)
    force_hold: dict = field(default_factory=dict)  # value, source [, cv_loss, loss_ratio]
    residual: np.ndarray | None = field(default=None, repr=False)
    verdict: Verdict = field(default_factory=Verdict)

    @property
    def m(self) -> float:
        return self.params["m"]

    @property
    def b(self) -> float:
        return self.params["b"]

    def as_dict(self) -> dict:
        return {
            "model": self.model,
            "method": self.method,
            **{k: self.params.get(k) for k in ("m", "b", "coulomb", "offset")},
            "ci95": {k: list(v) for k, v in self.ci95.items()},
            "rms_residual": self.rms_residual,
            "n_used": self.n_used,
            "explained": self.explained,
            "cutoff_hz": self.cutoff_hz,
            "flags": list(self.flags),
            "selection": self.selection,
            "force_hold": self.force_hold,
            "verdict": self.verdict.as_dict(),
        }


@dataclass
class _Data:
    y: np.ndarray  # force aligned with the derivatives
    cols: dict  # name -> regressor column
    x: np.ndarray  # raw position (kept samples)
    a_noise_gain: float
    v_noise_gain: float
    cutoff_hz: float
    fs: float

    def design(self, model: str) -> np.ndarray:
        return np.column_stack([self.cols[t] for t in TERMS[model]])


def identify(rec: Recording, model: str = "auto", method: str = "l2", cutoff_hz: float | None = None,
             solver: str = "fast", hold: str | None = None) -> IdResult:
    """Fit the device model to a recording (see module doc).

    ``hold``: "zoh" (force held over each sample interval, as a bench command
    is) or "sample" (force sampled at the same instants as position); None:
    the metadata ``force_hold``, else chosen by cross-validation
    (``IdResult.force_hold`` says which and why).
    """
    if model not in MODEL_CHOICES:
        raise UserError(f"unknown model {model!r}; choose one of {', '.join(MODEL_CHOICES)}")
    if method not in METHODS:
        raise UserError(f"unknown method {method!r}; choose l2 or l1")
    if solver not in SOLVERS:
        raise UserError(f"unknown solver {solver!r}; choose fast or cvxpy")
    fit = _fitter(method, solver)
    hold_info = _force_hold(rec, hold, cutoff_hz, method, fit)
    data = _prepare(rec, cutoff_hz, hold_info["value"])
    if not _identifiable(data, "mb"):
        raise UserError(f"{rec.source}: the position hardly moves (x' and x'' are not independent): "
                        "nothing to identify")
    selection = _select(data, fit, method) if model == "auto" else {"criterion": "given"}
    chosen = selection.get("model", model)
    if not _identifiable(data, chosen):
        raise UserError(f"model {chosen} cannot be identified from this record: the velocity never "
                        "changes sign, so Coulomb friction and a force offset look alike; use --model mbc or mb")
    X = data.design(chosen)
    theta = fit(X, data.y)
    resid = data.y - X @ theta
    ci = _jackknife_ci(X, data.y, theta, fit)
    params = dict(zip(TERMS[chosen], (float(v) for v in theta)))
    result = IdResult(
        model=chosen,
        method=method,
        params={k: params.get(k) for k in ("m", "b", "coulomb", "offset")},
        ci95={k: ci[i] for i, k in enumerate(TERMS[chosen])},
        rms_residual=float(np.sqrt(np.mean(resid**2))),
        n_used=len(data.y),
        explained=float(1 - np.var(resid) / np.var(data.y)) if np.var(data.y) > 0 else 0.0,
        cutoff_hz=data.cutoff_hz,
        selection=selection,
        force_hold=hold_info,
        residual=resid,
    )
    result.flags = _flags(result, data, fit, method, selection)
    result.verdict = _verdict(result, data)
    return result


def _verdict(res: IdResult, data: _Data) -> Verdict:
    """failed: a mass that is not positive, or a damping surely negative (no passive device
    has either: the model or the record is wrong); doubtful: b not resolved from 0, each
    flag in its own words, a model choice within UNDECIDED_SE of its threshold, or a residual
    that follows x''' (an unmodelled delay, see DELAY_SAMPLES)."""
    findings = []
    (m_lo, m_hi), (b_lo, b_hi) = res.ci95["m"], res.ci95["b"]
    if m_lo <= 0:
        findings.append((FAILED, f"m = {res.m:.4g} kg: its 95 % interval [{m_lo:.4g}, {m_hi:.4g}] "
                         "reaches 0 or below (no mass identified)"))
    if b_hi < 0:
        findings.append((FAILED, f"b = {res.b:.4g} N s/m is negative (95 % [{b_lo:.4g}, {b_hi:.4g}]): "
                         "a passive device cannot have it; an unstated delay or the wrong force_hold?"))
    elif b_lo <= 0:
        findings.append((DOUBTFUL, f"b is not resolved from 0: 95 % interval [{b_lo:.4g}, {b_hi:.4g}] N s/m"))
    findings += [(DOUBTFUL, f) for f in res.flags]
    for st in res.selection.get("steps", []):
        se = st.get("cv_gain_se")
        if se is not None and abs(se - MIN_GAIN_SE) < UNDECIDED_SE and st["why"] != "too small to matter":
            findings.append((DOUBTFUL, f"model choice undecided: {st['from']} -> {st['to']} gains "
                             f"{se:.2g} SE in cross-validation against a {MIN_GAIN_SE:g} SE threshold"))
    tau, share = _residual_delay(res, data)
    if abs(tau) > DELAY_SAMPLES / data.fs and share > DELAY_EXPLAINS:
        findings.append((DOUBTFUL, f"residual structure: {100 * share:.0f} % of the residual follows x''' as "
                         f"a delay of {1e3 * tau:.3g} ms between force and motion would leave it; state "
                         "the device delay (device_delay_s) or check the force timing"))
    return judge(findings)


def _residual_delay(res: IdResult, data: _Data) -> tuple[float, float]:
    """(tau [s], share): the residual regressed on m x''' (module doc of DELAY_SAMPLES):
    tau = coefficient, share = fraction of the residual variance it explains."""
    r = res.residual
    jerk = np.gradient(data.cols["m"]) * data.fs * res.m
    jj = float(jerk @ jerk)
    if r is None or jj == 0 or not np.any(r):
        return 0.0, 0.0
    tau = float(jerk @ r) / jj
    return tau, float(tau**2 * jj / (r @ r))


def _force_hold(rec: Recording, hold, cutoff_hz, method: str, fit) -> dict:
    """How the force reached the plant: given, from the metadata, or chosen by the data."""
    if hold is not None:
        return {"value": _check_hold(hold), "source": "given"}
    if rec.meta.get("force_hold") is not None:
        return {"value": _check_hold(rec.meta["force_hold"]), "source": "metadata"}
    losses = {}
    for h in HOLDS:
        data = _prepare(rec, cutoff_hz, h, filter_force=True)
        models = [m for m in MODELS if _identifiable(data, m)]
        if not models:
            return {"value": "zoh", "source": "default: the record cannot tell (it hardly moves)"}
        losses[h] = _cv_losses(data, fit, method, models[-1])
    best, other = sorted(HOLDS, key=lambda h: losses[h].mean())
    ratio = np.log(losses[other] / losses[best])
    se = np.std(ratio, ddof=1) / np.sqrt(len(ratio))
    decided = bool(ratio.mean() > max(MIN_GAIN_SE * se, np.log1p(HOLD_MIN_GAIN)))
    return {
        "value": best if decided else "zoh",
        "source": "cross-validation" if decided else
        f"cross-validation undecided (loss ratio within 2 SE or below {1 + HOLD_MIN_GAIN:g}): zoh, "
        "the bench's convention",
        "cv_loss": {h: float(v.mean()) for h, v in losses.items()},
        "loss_ratio": float(losses[other].mean() / losses[best].mean()),
        "model": models[-1],
    }


def _check_hold(hold) -> str:
    if hold not in HOLDS:
        raise UserError(f"force_hold must be zoh or sample, got {hold!r}")
    return hold


def _prepare(rec: Recording, cutoff_hz, hold: str, filter_force: bool = False) -> _Data:
    _check_hold(hold)
    fs = rec.fs
    if cutoff_hz is None:
        cutoff_hz = default_cutoff(rec.force, fs)
    elif not 0 < cutoff_hz < fs / 2:
        raise UserError(f"--cutoff must be between 0 and fs/2 = {fs / 2:g} Hz, got {cutoff_hz}")
    d = differentiate(rec.position, fs, cutoff_hz)
    f = np.asarray(rec.force, float)
    if filter_force or force_band(f, fs) > cutoff_hz / CUTOFF_FACTOR:
        # force has power the derivatives will not see: filter it the same way, so the
        # linear terms stay exact (a zero-phase filter commutes with m x'' + b x')
        f = lowpass(f, fs, cutoff_hz)
    if hold == "zoh":  # mean of the forces held over [t-T, t) and [t, t+T)
        f = np.concatenate([[f[0]], 0.5 * (f[1:] + f[:-1])])
    y = f[d.keep]
    q = position_quantum(rec.position) or 0.0
    v_sigma = q / np.sqrt(12) * d.noise_gain[0]  # velocity noise the encoder step leaves
    sign = special.erf(d.v_all / (np.sqrt(2) * v_sigma)) if v_sigma else np.sign(d.v_all)
    coulomb = lowpass(sign, fs, d.cutoff_hz)[d.keep]  # L sign(x'): see module doc
    cols = {"m": d.a, "b": d.v, "coulomb": coulomb, "offset": np.ones_like(d.v)}
    return _Data(y, cols, np.asarray(rec.position)[d.keep], d.noise_gain[1], d.noise_gain[0],
                 d.cutoff_hz, fs)


def _fitter(method: str, solver: str):
    if method == "l2":
        return lambda X, y, theta0=None: np.linalg.lstsq(X, y, rcond=None)[0]
    if solver == "cvxpy":
        return lambda X, y, theta0=None: l1.lad_cvxpy(X, y)
    return l1.lad


def _loss(method: str, r: np.ndarray) -> float:
    return float(np.mean(r**2) if method == "l2" else np.mean(np.abs(r)))


def _blocks(n: int, count: int) -> list[np.ndarray]:
    edges = np.linspace(0, n, count + 1).astype(int)
    return [np.arange(edges[i], edges[i + 1]) for i in range(count)]


def _cv_losses(data: _Data, fit, method: str, model: str) -> np.ndarray:
    X, y = data.design(model), data.y
    blocks = _blocks(len(y), CV_BLOCKS)
    losses = []
    for k in range(CV_FOLDS):
        test = np.concatenate(blocks[k::CV_FOLDS])
        train = np.setdiff1d(np.arange(len(y)), test, assume_unique=True)
        theta = fit(X[train], y[train])
        losses.append(_loss(method, y[test] - X[test] @ theta))
    return np.array(losses)


def _identifiable(data: _Data, model: str) -> bool:
    X = data.design(model)
    scale = np.sqrt(np.mean(X**2, axis=0))
    return bool(np.all(scale > 0)) and np.linalg.matrix_rank(X / scale) == X.shape[1]


def _select(data: _Data, fit, method: str) -> dict:
    models = [m for m in MODELS if _identifiable(data, m)]
    losses = {m: _cv_losses(data, fit, method, m) for m in models}
    floor = _loss(method, MIN_GAIN_FORCE * np.full(1, np.sqrt(np.mean(data.y**2))))
    if method == "l1":
        floor = MIN_GAIN_FORCE * float(np.mean(np.abs(data.y)))
    chosen, steps = models[0], []
    for bigger in models[1:]:
        step = _step(data, fit, method, chosen, bigger, losses, floor)
        steps.append(step)
        if step["accepted"]:
            chosen = bigger
    return {
        "criterion": f"blocked {CV_FOLDS}-fold cross-validation, {method} loss; a larger model must "
        f"win by > {MIN_GAIN_SE:g} SE, > {100 * MIN_GAIN_REL:g} % and > a {100 * MIN_GAIN_FORCE:g} % force "
        f"floor, and its new term be >= {100 * TERM_VS_FORCE:g} % of the force rms and >= "
        f"{100 * TERM_VS_RESIDUAL:g} % of the residual rms",
        "model": chosen,
        "cv_loss": {m: float(v.mean()) for m, v in losses.items()},
        "steps": steps,
        "reason": _reason(chosen, steps),
    }


def _step(data: _Data, fit, method: str, smaller: str, bigger: str, losses: dict, floor: float) -> dict:
    """One comparison smaller -> bigger: cross-validated gain and physical size of the new term."""
    term = TERMS[bigger][-1]
    ratio = np.log(losses[smaller] / losses[bigger])  # per fold; > 0 when bigger predicts better
    se = float(np.std(ratio, ddof=1) / np.sqrt(len(ratio)))
    gain = float(losses[smaller].mean() - losses[bigger].mean())
    X = data.design(bigger)
    theta = fit(X, data.y)
    size = abs(float(theta[-1]))
    force_rms = float(np.sqrt(np.mean(data.y**2)))
    resid_rms = float(np.sqrt(np.mean((data.y - X @ theta) ** 2)))
    step = {
        "from": smaller, "to": bigger, "term": term, "value": float(theta[-1]),
        "cv_gain_rel": float(-np.expm1(-ratio.mean())), "cv_gain_se": float(ratio.mean() / se) if se else None,
        "vs_force_rms": size / force_rms, "vs_residual_rms": size / resid_rms if resid_rms else None,
    }
    supported = ratio.mean() > max(MIN_GAIN_SE * se, np.log1p(MIN_GAIN_REL))
    significant = size >= TERM_VS_FORCE * force_rms and size >= TERM_VS_RESIDUAL * resid_rms
    step["accepted"] = bool(supported and gain > floor and significant)
    step["why"] = ("accepted" if step["accepted"] else
                   "not supported by cross-validation" if not supported else
                   "CV gain below the force floor" if gain <= floor else
                   "too small to matter")
    return step


def _reason(chosen: str, steps: list) -> str:
    parts = []
    for st in steps:
        name = {"coulomb": "Coulomb", "offset": "offset"}[st["term"]]
        detail = (f"{name} {st['value']:.3g} N: CV loss {-100 * st['cv_gain_rel']:+.1f} %"
                  + (f" ({st['cv_gain_se']:.1f} SE)" if st["cv_gain_se"] is not None else "")
                  + f", {100 * st['vs_force_rms']:.2g} % of the force rms")
        if st["vs_residual_rms"] is not None:
            detail += f", {st['vs_residual_rms']:.2g}x the residual rms"
        parts.append(f"{st['to']} {'accepted' if st['accepted'] else 'rejected, ' + st['why']} ({detail})")
    return f"{chosen}" + (": " + "; ".join(parts) if parts else ": the only identifiable model")


def _jackknife_ci(X, y, theta, fit) -> list[tuple[float, float]]:
    blocks = _blocks(len(y), JACKKNIFE_BLOCKS)
    G = len(blocks)
    reps = []
    for blk in blocks:
        keep = np.ones(len(y), bool)
        keep[blk] = False
        reps.append(fit(X[keep], y[keep], theta))
    reps = np.array(reps)
    se = np.sqrt((G - 1) / G * np.sum((reps - reps.mean(axis=0)) ** 2, axis=0))
    t = stats.t.ppf(0.975, G - 1)
    return [(float(c - t * s), float(c + t * s)) for c, s in zip(theta, se)]


def _flags(res: IdResult, data: _Data, fit, method: str, selection: dict) -> list[str]:
    flags = []
    if res.n_used < SHORT_RECORD:
        flags.append(f"short-record: only {res.n_used} samples used (< {SHORT_RECORD}); "
                     "treat the estimates as rough")
    for k in ("m", "b"):
        lo, hi = res.ci95[k]
        val = res.params[k]
        if not (hi - lo) / 2 <= WIDE_CI_REL * abs(val):
            flags.append(f"wide-interval: {k} 95 % interval [{lo:.4g}, {hi:.4g}] is wider than "
                         f"+-{100 * WIDE_CI_REL:g} % (little excitation or a short record?)")
    n_out = _count_outliers(res.residual, MIN_GAIN_FORCE * np.sqrt(np.mean(data.y**2)))
    if n_out:
        what = "l1 resists them" if method == "l1" else "l2 is pulled by them: try --method l1"
        flags.append(f"force-outliers: {n_out} isolated force spikes beyond {OUTLIER_SIGMAS:g} local robust sigmas; {what}")
    if res.params["coulomb"] is None:
        sel = selection if "model" in selection else _select(data, fit, method)
        if sel["model"] != "mb":
            mbc = float(fit(data.design(sel["model"]), data.y)[2])
            flags.append(f"unmodelled-coulomb: a Coulomb term of {mbc:.3g} N is supported by the data; "
                         "use --model mbc or auto")
    q = position_quantum(data.x)
    if q:
        a_sig = np.std(data.cols["m"])
        rel = q / np.sqrt(12) * data.a_noise_gain / max(a_sig, 1e-300)
        if rel > QUANT_NOISE_REL:
            flags.append(f"quantised-position: encoder step {q:.3g} m makes x'' noise {100 * rel:.1f} % "
                         f"of its signal (m biased low by ~{100 * rel**2 / (1 + rel**2):.1f} %); "
                         "lower --cutoff or use more excitation")
    stuck = _stuck_fraction(data, q or 0.0)
    if stuck > STICK_FRACTION:
        flags.append(f"stick-slip: the handle is at rest under a nonzero force for {100 * stuck:.0f} % "
                     "of the samples; there the friction force is anything up to the Coulomb level, "
                     "f = m x'' + b x' + Fc sign(x') does not hold, and b and Coulomb may be biased "
                     "(b typically high): raise the excitation so the handle keeps moving")
    return flags


def _stuck_fraction(data: _Data, q: float) -> float:
    """Fraction of samples at rest (|x'| below the velocity noise that the encoder step
    q leaves after the derivative filter) while the force is not near zero.

    A stuck handle (|f| <= Fc, x' = 0) breaks the sliding-friction model: the
    friction force is then whatever balances f, not Fc sign(x').
    """
    v = data.cols["b"]
    v_rest = max(REST_SIGMAS * q / np.sqrt(12) * data.v_noise_gain, REST_REL * float(np.std(v)))
    pushed = np.abs(data.y) > STICK_FORCE_REL * np.sqrt(np.mean(data.y**2))
    return float(np.mean((np.abs(v) < v_rest) & pushed))


def _count_outliers(r: np.ndarray, floor: float) -> int:
    """Isolated spikes: samples whose residual departs from the 5-point running median
    by more than OUTLIER_SIGMAS x the robust scale (1.4826 MAD) of the residual in
    their own block of OUTLIER_BLOCK samples, and by more than ``floor``.

    The running median follows smooth or step-like residuals (a chirp's growing
    error, unmodelled friction), so only spikes such as force-sensor glitches count.
    """
    d = np.abs(r - ndimage.median_filter(r, size=5, mode="nearest"))
    n = len(d) // OUTLIER_BLOCK * OUTLIER_BLOCK
    if n == 0:
        return 0
    rb = r[:n].reshape(-1, OUTLIER_BLOCK)
    scale = 1.4826 * np.median(np.abs(rb - np.median(rb, axis=1, keepdims=True)), axis=1, keepdims=True)
    return int(np.sum(d[:n].reshape(-1, OUTLIER_BLOCK) > np.maximum(OUTLIER_SIGMAS * scale, floor)))
