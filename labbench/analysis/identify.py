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
biases Fc low by ~10 % and b high). The sign is the expected one given what the
filtered velocity does not know of the true one, erf(x' / (sqrt(2) s_v)) (regression
calibration: a regressor seen with error replaced by its expectation given what is
seen, consistent for a model linear in its parameters; Carroll, Ruppert, Stefanski &
Crainiceanu, *Measurement Error in Nonlinear Models*, 2nd ed. 2006, ch. 4): s_v holds
the encoder's noise, q / sqrt(12) x the filter's noise gain, so a sign flipped by it
near rest is not taken for friction, and the velocity beyond the cut-off
(``derivatives.velocity_beyond``, with the mass of a least-squares pass), independent
of the filtered velocity where the two bands do not overlap. The latter matters under
white noise, whose power runs past the cut-off: the true velocity then reverses on a
time scale the filter does not resolve (5 mm/s beyond 50 Hz at 0.5 N on a 0.094 kg
handle), and the filtered sign over-states where friction switched: Fc read 17 % low
(0.0165 for 0.02 N) and b high before; a chirp's band stays below the cut-off.

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

Encoder step: the quantisation noise q^2 / 12 of the position reaches x'' and x' with
the derivative filter's known gains, and noise in a regressor attenuates least
squares; l2 is corrected, theta = (X'X - n Sigma)^-1 X'y (Fuller, Measurement Error
Models, 1987, sec. 2.2). Closed-loop records (``response`` given): the motion follows
any force the record lacks, so the regressors correlate with the residual; l2 then
uses instrumental variables, the regressors of the loop's response to the exogenous
force alone (``_instruments``).

95 % intervals: the estimator's estimating equations summed over windows of contiguous
samples, each window's share corrected for its leverage (``_sandwich_ci``): robust to the
strong serial correlation of filtered residuals and to a record whose information sits in
a few seconds (a chirp's damping); theta +- t(0.975, dof) * se with Satterthwaite's dof.
They also cover what
the data cannot decide: both models of an undecided selection step, and for a model
with Coulomb friction the fit away from velocity reversals (``_away_from_reversals``).
"""
from __future__ import annotations

import threading
from collections.abc import Callable
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
    velocity_beyond,
)
from labbench.analysis.progress import Progress, Steps
from labbench.errors import UserError
from labbench.readout.verdict import BIAS_SE, DOUBTFUL, FAILED, Verdict, judge, precision

MODELS = ("mb", "mbc", "mbco")
MODEL_CHOICES = MODELS + ("auto",)
METHODS = ("l2", "l1")
SOLVERS = ("fast", "cvxpy")
TERMS = {"mb": ("m", "b"), "mbc": ("m", "b", "coulomb"), "mbco": ("m", "b", "coulomb", "offset")}
CV_FOLDS, CV_BLOCKS = 5, 20
# interval windows: BLOCK_CORR x fs / cutoff samples (about 5x the correlation length the
# derivative filter leaves, ~2 fs / cutoff), at least MIN_BLOCKS of them in the record
BLOCK_CORR, MIN_BLOCKS = 10, 10
WINDOW_STEPS = 4  # windows start every quarter of a window (``_sandwich_ci``)
LEVERAGE_FLOOR = 1e-12  # 1 - a window's leverage, at least (``_sandwich_ci``)
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
LS_COND = 1e6  # condition number of the scaled normal equations up to which least_squares uses them
UNDECIDED_SE = 1.0  # a model step within this many SE of the MIN_GAIN_SE threshold is undecided
IV_PASSES = 2  # instrumental-variable passes, each simulating the loop with the last estimate
M_TARGET, B_TARGET = 0.01, 0.02  # issue 24's accuracy targets of identification (relative)
MIN_AWAY = 0.1  # the fit away from velocity reversals needs this share of the samples
REVERSAL_REACH = 1.5  # x fs / cutoff: how far from a reversal its misfit reaches through the filter


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
    hold: str = "zoh"
    noise_var: dict = field(default_factory=dict)  # name -> variance the encoder step adds to the column

    def design(self, model: str) -> np.ndarray:
        return _columns(self.cols, TERMS[model])

    def noise(self, model: str) -> np.ndarray:
        """Variance the encoder step adds to each regressor of ``model``."""
        return np.array([self.noise_var.get(t, 0.0) for t in TERMS[model]])


def identify(rec: Recording, model: str = "auto", method: str = "l2", cutoff_hz: float | None = None,
             solver: str = "fast", hold: str | None = None,
             response: Callable[[float, float], np.ndarray] | None = None,
             progress: Progress | None = None, cancel: threading.Event | None = None,
             coulomb_n: float | None = None) -> IdResult:
    """Fit the device model to a recording (see module doc).

    ``hold``: "zoh" (force held over each sample interval, as a bench command
    is) or "sample" (force sampled at the same instants as position); None:
    the metadata ``force_hold``, else chosen by cross-validation
    (``IdResult.force_hold`` says which and why). ``response``: for a closed-loop record
    whose force is what the plant felt (``compare.plant_recording``), ``(m, b) ->`` the
    position the loop would have on its exogenous force alone (``compare.loop_response``):
    m and b then come from instrumental variables (module doc). ``progress``, ``cancel``:
    ``labbench.analysis.progress`` (Cancelled once ``cancel`` is set). ``coulomb_n``: a
    known Coulomb level [N] (a chirp-ID's): its force, Fc L sign(x'), is taken off the
    force and m, b are fitted (model mb), so friction is not read as viscous damping.
    """
    if coulomb_n is not None:
        model = "mb"
    if model not in MODEL_CHOICES:
        raise UserError(f"unknown model {model!r}; choose one of {', '.join(MODEL_CHOICES)}")
    if method not in METHODS:
        raise UserError(f"unknown method {method!r}; choose l2 or l1")
    if solver not in SOLVERS:
        raise UserError(f"unknown solver {solver!r}; choose fast or cvxpy")
    steps = Steps(progress, cancel)
    fit = _Fit(method, solver, steps.check)
    steps.report(0.0, "reading how the force was held")
    hold_info = _force_hold(rec, hold, cutoff_hz, method, fit, steps.check)
    steps.report(0.3, "derivatives")
    data = _prepare(rec, cutoff_hz, hold_info["value"], check=steps.check)
    if coulomb_n:
        data.y = data.y - coulomb_n * data.cols["coulomb"]
    if not _identifiable(data, "mb"):
        raise UserError(f"{rec.source}: the position hardly moves (x' and x'' are not independent): "
                        "nothing to identify")
    steps.report(0.35, "selecting the model")
    selection = _select(data, fit, method) if model == "auto" else {"criterion": "given"}
    steps.report(0.75, "estimating with intervals")
    chosen = selection.get("model", model)
    if not _identifiable(data, chosen):
        raise UserError(f"model {chosen} cannot be identified from this record: the velocity never "
                        "changes sign, so Coulomb friction and a force offset look alike; use --model mbc or mb")
    closed = response is not None and method == "l2"
    inst = _instruments(data, response, fit, method, chosen, steps.check) if closed else None
    theta, resid, ci = _estimate(data, fit, method, chosen, inst=inst)
    # a model step the data cannot decide (within UNDECIDED_SE of its threshold) leaves both
    # models standing: the intervals cover the parameters under either (module doc)
    for st in selection.get("steps", []):
        se = st.get("cv_gain_se")
        if se is not None and abs(se - MIN_GAIN_SE) < UNDECIDED_SE and st["why"] != "too small to matter":
            other = _other_model(chosen, st["term"])
            if other is not None and _identifiable(data, other):
                _, _, ci_other = _estimate(data, fit, method, other, inst=inst)
                for k, (lo, hi) in ci_other.items():
                    if k in ci:
                        ci[k] = (min(ci[k][0], lo), max(ci[k][1], hi))
                st["intervals_cover"] = [chosen, other]
    if "coulomb" in TERMS[chosen]:
        # friction's model is least exact at velocity reversals (switching inside a sample,
        # sticking): the intervals also cover the fit away from them (module doc)
        away = _away_from_reversals(data)
        if away.sum() >= MIN_AWAY * len(away):
            _, _, ci_away = _estimate(data, fit, method, chosen, away, inst)
            for k, (lo, hi) in ci_away.items():
                ci[k] = (min(ci[k][0], lo), max(ci[k][1], hi))
    params = dict(zip(TERMS[chosen], (float(v) for v in theta)))
    result = IdResult(
        model=chosen,
        method=method,
        params={k: params.get(k) for k in ("m", "b", "coulomb", "offset")},
        ci95=ci,
        rms_residual=float(np.sqrt(np.mean(resid**2))),
        n_used=len(data.y),
        explained=float(1 - np.var(resid) / np.var(data.y)) if np.var(data.y) > 0 else 0.0,
        cutoff_hz=data.cutoff_hz,
        selection=selection,
        force_hold=hold_info,
        residual=resid,
    )
    if inst is not None:
        result.selection["estimator"] = "instrumental variables (the loop's response to the exogenous force)"
    steps.report(0.95, "checking the fit")
    result.flags = _flags(result, data, fit, method, selection)
    if response is not None and method == "l1":
        result.flags.append("closed-loop-l1: the motion of a closed loop follows any force the record "
                            "lacks, which biases l1 (l2 uses instrumental variables against it)")
    result.verdict = _verdict(result, data)
    steps.report(1.0, "identified")
    return result


def _columns(cols: dict, names) -> np.ndarray:
    """The n x p matrix of the named columns, column-major: X @ theta on a long row-major
    n x p array took 7x as long (OpenBLAS's gemv, p <= 4)."""
    X = np.empty((len(cols[names[0]]), len(names)), order="F")
    for j, name in enumerate(names):
        X[:, j] = cols[name]
    return X


def _estimate(data: _Data, fit, method: str, model: str, keep=None,
              inst=None) -> tuple[np.ndarray, np.ndarray, dict]:
    """(theta, residual, 95 % intervals by name) of one model on the samples ``keep`` (all by
    default): l2 corrected for the encoder's noise in the regressors, or with the instrument
    columns ``inst`` (name -> column) instrumental variables (module doc); intervals from
    ``_sandwich_ci``."""
    rows = np.arange(len(data.y)) if keep is None else np.flatnonzero(keep)
    X, y = data.design(model), data.y
    Z = None if inst is None else _columns(inst, TERMS[model])
    if keep is not None:
        X, y, Z = np.asfortranarray(X[rows]), y[rows], None if Z is None else np.asfortranarray(Z[rows])
    noise = data.noise(model) if method == "l2" and Z is None else np.zeros(X.shape[1])
    if Z is not None:  # the instruments know nothing of the noise: no correction needed
        theta = np.linalg.solve(Z.T @ X, Z.T @ y)
    else:
        theta = fit(X, y)
        if noise.any():
            G = X.T @ X
            theta = np.linalg.solve(G - len(y) * np.diag(noise), G @ theta)
    resid = y - X @ theta
    ci = _sandwich_ci(X, resid, theta, method, noise, data.fs / data.cutoff_hz, rows, Z)
    return theta, resid, dict(zip(TERMS[model], ci))


def _instruments(data: _Data, response, fit, method: str, model: str, check=lambda: None) -> dict:
    """Instrument columns for a closed-loop record: the regressors of the loop's response to
    the exogenous force alone (refined instrumental variables, Soderstrom & Stoica, System
    Identification, 1989, ch. 8): uncorrelated with any force the record lacks, which the
    measured motion follows. Two passes, each simulated with the previous estimate (least
    squares first); friction and offset columns stand for themselves."""
    theta = fit(data.design(model), data.y)
    inst = None
    for _ in range(IV_PASSES):
        check()
        x = response(max(theta[0], 1e-9), max(theta[1], 0.0))
        check()
        d = differentiate(x, data.fs, data.cutoff_hz, data.hold)
        check()
        inst = {**data.cols, "m": d.a, "b": d.v}
        theta, _, _ = _estimate(data, fit, method, model, inst=inst)
    return inst


def _away_from_reversals(data: _Data) -> np.ndarray:
    """Samples farther than the derivative filter's reach (REVERSAL_REACH fs / cutoff) from every reversal
    of the velocity: there friction switches, the handle may stick and the sampled model is
    least exact (module doc)."""
    reach = int(np.ceil(REVERSAL_REACH * data.fs / data.cutoff_hz))
    rev = np.flatnonzero(np.diff(np.sign(data.cols["b"])) != 0)
    near = np.zeros(len(data.y) + 1, int)
    np.add.at(near, np.clip(rev - reach, 0, len(data.y)), 1)
    np.add.at(near, np.clip(rev + reach + 1, 0, len(data.y)), -1)
    return np.cumsum(near)[:-1] == 0


def _other_model(chosen: str, term: str) -> str | None:
    """The model an undecided step about ``term`` would have given instead of ``chosen``."""
    terms = set(TERMS[chosen]) ^ {term}
    return next((m for m in MODELS if set(TERMS[m]) == terms), None)


# What each flag says of the numbers (labbench.readout.verdict): a bias their intervals may not hold
# (a doubt), or only how precise they are (a note: the intervals say it)
PRECISION_FLAGS = ("short-record", "wide-interval")
# a bias below this share of a number's accuracy target is within it (a note, not a doubt)
BIAS_OF_TARGET = 0.5
# the white-noise model of an encoder step corrects l2's m to about this share of the
# correction (measured on exact chirps: 100 um, 0.23 % corrected to 0.01 %; 300 um, 2 % to 0.2 %)
QUANT_MODEL_SHARE = 0.15


def _verdict(res: IdResult, data: _Data) -> Verdict:
    """failed: a mass that is not positive, or a damping surely negative (no passive device
    has either: the model or the record is wrong); doubtful: a flag naming a bias (stick-slip,
    force outliers pulling l2, unmodelled friction, an encoder step whose effect on m may
    exceed ``BIAS_OF_TARGET`` of M_TARGET), or a residual that follows the third derivative
    (an unmodelled delay, see DELAY_SAMPLES). How precise m and b are (b not resolved from 0,
    an interval wider than the targets M_TARGET, B_TARGET: ``labbench.readout.verdict.precision``)
    is a note."""
    findings, notes = [], []
    (m_lo, m_hi), (b_lo, b_hi) = res.ci95["m"], res.ci95["b"]
    if m_lo <= 0:
        findings.append((FAILED, f"m = {res.m:.4g} kg: its 95 % interval [{m_lo:.4g}, {m_hi:.4g}] "
                         "reaches 0 or below (no mass identified)"))
    if b_hi < 0:
        findings.append((FAILED, f"b = {res.b:.4g} N s/m is negative (95 % [{b_lo:.4g}, {b_hi:.4g}]): "
                         "a passive device cannot have it; an unstated delay or the wrong force_hold?"))
    elif b_lo <= 0:
        notes.append(f"b is not resolved from 0: 95 % interval [{b_lo:.4g}, {b_hi:.4g}] N s/m")
    for f in res.flags:
        if _is_bias(f, res, data):
            findings.append((DOUBTFUL, f))
        else:
            notes.append(f)
    undecided = [f"{st['from']} -> {st['to']}" for st in res.selection.get("steps", [])
                 if "intervals_cover" in st]
    why = (f" (the intervals hold the undecided model step {', '.join(undecided)} either way)"
           if undecided else "")
    for k, target, unit in (("m", M_TARGET, " kg"), ("b", B_TARGET, " N s/m")):
        note = precision(k, res.params[k], res.ci95[k], target * abs(res.params[k]), unit)
        notes.append(note and note + why)
    tau, share = _residual_delay(res, data)
    if abs(tau) > DELAY_SAMPLES / data.fs and share > DELAY_EXPLAINS:
        findings.append((DOUBTFUL, f"residual structure: {100 * share:.0f} % of the residual follows x''' as "
                         f"a delay of {1e3 * tau:.3g} ms between force and motion would leave it; state "
                         "the device delay (device_delay_s) or check the force timing"))
    return judge(findings, notes=notes)


def _is_bias(flag: str, res: IdResult, data: _Data) -> bool:
    """Whether a flag names a bias the intervals may not hold (the constants above)."""
    name = flag.split(":", 1)[0]
    if name in PRECISION_FLAGS:
        return False
    if name == "force-outliers":
        return res.method != "l1"  # l1 resists them
    if name == "quantised-position":
        share = QUANT_MODEL_SHARE if res.method == "l2" else 1.0  # l2 corrects it, l1 does not
        return share * _quant_attenuation(data) > BIAS_OF_TARGET * M_TARGET
    return True


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


def _force_hold(rec: Recording, hold, cutoff_hz, method: str, fit, check=lambda: None) -> dict:
    """How the force reached the plant: given, from the metadata, or chosen by the data."""
    if hold is not None:
        return {"value": _check_hold(hold), "source": "given"}
    if rec.meta.get("force_hold") is not None:
        return {"value": _check_hold(rec.meta["force_hold"]), "source": "metadata"}
    losses = {}
    for h in HOLDS:
        data = _prepare(rec, cutoff_hz, h, filter_force=True, check=check)
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


def _prepare(rec: Recording, cutoff_hz, hold: str, filter_force: bool = False,
             check=lambda: None) -> _Data:
    """Regressors and force of a record (module doc); ``check`` between its passes over the
    data (it raises to cancel)."""
    _check_hold(hold)
    fs = rec.fs
    f = np.asarray(rec.force, float)
    band = force_band(f, fs)  # an FFT of the record: once
    if cutoff_hz is None:
        cutoff_hz = default_cutoff(band, fs)
    elif not 0 < cutoff_hz < fs / 2:
        raise UserError(f"--cutoff must be between 0 and fs/2 = {fs / 2:g} Hz, got {cutoff_hz}")
    check()
    d = differentiate(rec.position, fs, cutoff_hz, hold)
    check()
    if filter_force or band > cutoff_hz / CUTOFF_FACTOR:
        # force has power the derivatives will not see: filter it the same way, so the
        # linear terms stay exact (a zero-phase filter commutes with m x'' + b x')
        f = lowpass(f, fs, cutoff_hz)
    if hold == "zoh":  # mean of the forces held over [t-T, t) and [t, t+T)
        f = np.concatenate([[f[0]], 0.5 * (f[1:] + f[:-1])])
    y = f[d.keep]
    q = position_quantum(rec.position) or 0.0
    # what the filtered velocity does not know of the true one: the encoder step's noise and
    # the velocity beyond the cut-off (module doc: the sign's expectation given both)
    mass = float(np.linalg.lstsq(np.column_stack([d.a, d.v]), y, rcond=None)[0][0])
    v_sigma = float(np.hypot(q / np.sqrt(12) * d.noise_gain[0],
                             velocity_beyond(rec.force, fs, d.cutoff_hz, mass)))
    sign = special.erf(d.v_all / (np.sqrt(2) * v_sigma)) if v_sigma else np.sign(d.v_all)
    check()
    coulomb = lowpass(sign, fs, d.cutoff_hz)[d.keep]  # L sign(x'): see module doc
    cols = {"m": d.a, "b": d.v, "coulomb": coulomb, "offset": np.ones_like(d.v)}
    enc = q**2 / 12  # white quantisation noise of the position
    return _Data(y, cols, np.asarray(rec.position)[d.keep], d.noise_gain[1], d.noise_gain[0],
                 d.cutoff_hz, fs, hold, {"m": enc * d.noise_gain[1] ** 2, "b": enc * d.noise_gain[0] ** 2})


class _Fit:
    """The fit of one design matrix by ``method``; ``check`` before it (and between l1's
    steps): it raises to cancel."""

    def __init__(self, method: str, solver: str, check: Callable[[], None]):
        self.method, self.solver, self.check = method, solver, check

    def __call__(self, X: np.ndarray, y: np.ndarray, theta0=None) -> np.ndarray:
        if self.method == "l1" and self.solver == "fast":
            return l1.lad(X, y, theta0, self.check)
        self.check()
        return least_squares(X, y) if self.method == "l2" else l1.lad_cvxpy(X, y)


def least_squares(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least squares by the normal equations of the columns scaled to unit norm, refined once
    with the residual (theta += G^-1 X'r): squaring the condition number costs digits that
    the refinement restores while cond^2 eps << 1, as for these designs (else, and for a
    singular one, LAPACK's SVD solver). Streaming passes over X, whose cost per row stays
    flat with the record's length: LAPACK's solver took 11 ns a row at 120 000 samples and
    19 ns at 1.8 M (its Householder passes leave the cache)."""
    solve = _normal_solver(X.T @ X)
    if solve is None:
        return np.linalg.lstsq(X, y, rcond=None)[0]
    theta = solve(X.T @ y)
    return theta + solve(X.T @ (y - X @ theta))


def _normal_solver(G: np.ndarray):
    """v -> G^-1 v through G scaled to a unit diagonal; None when a column is zero or the
    scaled G's condition number reaches LS_COND."""
    s = np.sqrt(np.diag(G))
    if not np.all(s > 0):
        return None
    Gs = G / np.outer(s, s)
    if not np.linalg.cond(Gs) < LS_COND:
        return None
    return lambda v: np.linalg.solve(Gs, v / s) / s


def _loss(method: str, r: np.ndarray) -> float:
    return float(np.mean(r**2) if method == "l2" else np.mean(np.abs(r)))


def _blocks(n: int, count: int) -> list[slice]:
    edges = np.linspace(0, n, count + 1).astype(int)
    return [slice(edges[i], edges[i + 1]) for i in range(count)]


def _cv_losses(data: _Data, fit: _Fit, method: str, model: str) -> np.ndarray:
    X, y = data.design(model), data.y
    blocks = _blocks(len(y), CV_BLOCKS)
    if fit.method == "l2":
        return _cv_losses_l2(X, y, blocks, fit.check)
    losses = []
    for k in range(CV_FOLDS):
        test = np.r_[tuple(blocks[k::CV_FOLDS])]
        keep = np.ones(len(y), bool)
        keep[test] = False
        train = np.flatnonzero(keep)
        theta = fit(X[train], y[train])
        losses.append(_loss(method, y[test] - X[test] @ theta))
    return np.array(losses)


def _cv_losses_l2(X, y, blocks: list[slice], check) -> np.ndarray:
    """The l2 folds without copying their rows: each fold's normal equations are the sums of
    its training blocks' (computed once), refined with the residuals of the blocks in place
    (``least_squares``); the test loss from the test blocks in place."""
    check()
    grams = [(X[b].T @ X[b], X[b].T @ y[b]) for b in blocks]
    losses = []
    for k in range(CV_FOLDS):
        check()
        train = [i for i in range(len(blocks)) if i % CV_FOLDS != k]
        solve = _normal_solver(sum(grams[i][0] for i in train))
        if solve is None:
            rows = np.r_[tuple(blocks[i] for i in train)]
            theta = np.linalg.lstsq(X[rows], y[rows], rcond=None)[0]
        else:
            theta = solve(sum(grams[i][1] for i in train))
            theta = theta + solve(sum(X[blocks[i]].T @ (y[blocks[i]] - X[blocks[i]] @ theta) for i in train))
        test = blocks[k::CV_FOLDS]
        sq = sum(float(np.sum((y[b] - X[b] @ theta) ** 2)) for b in test)
        losses.append(sq / sum(b.stop - b.start for b in test))
    return np.array(losses)


def _identifiable(data: _Data, model: str) -> bool:
    """Whether no regressor of ``model`` is a linear combination of the others (the rank
    test of ``l1.independent_columns``, columns scaled)."""
    X = data.design(model)
    return len(l1.independent_columns(X)) == X.shape[1]


def _select(data: _Data, fit, method: str) -> dict:
    models = []
    for m in MODELS:
        fit.check()  # each test is a QR over every sample
        if _identifiable(data, m):
            models.append(m)
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


def _sandwich_ci(X, r, theta, method: str, noise: np.ndarray, corr_samples: float,
                 rows: np.ndarray, Z=None) -> list[tuple[float, float]]:
    """95 % intervals from the estimator's estimating equations summed over windows of
    contiguous samples (module doc): l2 psi_k = x_k r_k (+ noise * theta, the corrected
    equation), D = X'X - n noise; l1 psi_k = x_k sign(r_k) / 2, D = f(0) X'X, f(0) the
    residuals' density at 0, #{|r_k| <= h} / (2 h n) with the Hall-Sheather bandwidth h
    (Koenker, Quantile Regression, 2005, sec. 3.4; Powell's local sum_{|r_k| <= h} x_k x_k' /
    (2 h) read b's entry off the few near-zero residuals of the few windows that carry b: its
    noise left l1's b intervals at 93.7 % on 300 records, one density 95.3 %); with
    instruments ``Z``: psi_k = z_k r_k, D = Z'X.

    Each window w contributes u_w = (I - D^-1 D_w)^(-1/2) D^-1 s_w, s_w and D_w its own sums
    of psi and of D's terms: Bell & McCaffrey's bias-reduced linearisation (CR2; Survey
    Methodology 28, 2002), for least squares the window's residuals scaled by
    (I - H_ww)^(-1/2), H its leverage. The plain D^-1 s_w comes from residuals the window
    itself pulled towards it: where a few windows carry a parameter's information (a chirp's
    damping sits in its slow seconds) b's intervals were 15 % narrow in variance (coverage
    l2 93.7 %, l1 90.0 % on 300 records of issue 30's grid; with CR2 95.0 % and 93.7 %; the
    jackknife's (I - D^-1 D_w)^-1, CR3, gave 97 % and 95 %). Windows of about BLOCK_CORR x
    fs / cutoff samples start every 1 / WINDOW_STEPS of a window (overlapping batch means,
    Meketon & Schmeiser 1984, on a stride that keeps the p x p eigenproblems few); var =
    sum_w u_w u_w' / (steps per window). The t quantile has Satterthwaite's dof over the
    non-overlapping windows, (sum u^2)^2 / (sum u^4 / 3), x 1.5 for the overlap (few
    windows carrying a chirp's damping: few dof)."""
    n, p = X.shape
    if Z is not None:
        A, psi = Z, Z * r[:, None]
    elif method == "l2":
        A, psi = X, X * r[:, None] + noise * theta
    else:
        hs = n ** (-1 / 3) * stats.norm.ppf(0.975) ** (2 / 3) * (1.5 * stats.norm.pdf(0) ** 2) ** (1 / 3)
        scale = min(np.std(r), stats.iqr(r) / 1.349)
        h = max(2 * stats.norm.ppf(0.5 + hs) * scale, np.finfo(float).tiny)
        A, psi = X * (np.count_nonzero(np.abs(r) <= h) / (2 * h * n)), X * (np.sign(r) / 2)[:, None]
    span = int(rows[-1]) + 1  # samples in time order; a subset leaves zeros between its rows
    length = min(max(int(np.ceil(BLOCK_CORR * corr_samples)), 1), max(span // MIN_BLOCKS, 1))
    step = max(length // WINDOW_STEPS, 1)
    per = max(length // step, 1)  # steps per window
    count = -(-span // step)
    # sums of psi and of D's terms over each step of `step` samples
    slot = rows // step
    s_steps = np.zeros((count, p))
    d_steps = np.zeros((count, p, p))
    for i in range(p):
        s_steps[:, i] = np.bincount(slot, psi[:, i], count)
        for j in range(p):
            d_steps[:, i, j] = np.bincount(slot, A[:, i] * X[:, j], count)
    if noise.any():
        d_steps -= np.bincount(slot, minlength=count)[:, None, None] * np.diag(noise)
    D = d_steps.sum(axis=0)
    c_s = np.concatenate([np.zeros((1, p)), np.cumsum(s_steps, axis=0)])
    c_d = np.concatenate([np.zeros((1, p, p)), np.cumsum(d_steps, axis=0)])
    windows = max(count - per + 1, 1)
    s_w = c_s[per:per + windows] - c_s[:windows]
    d_w = c_d[per:per + windows] - c_d[:windows]
    Dinv = np.linalg.pinv(D)
    # (I - P)^(-1/2) through P's eigenvectors; an eigenvalue of I - P at or below 0 is a
    # window holding all of some parameter's information: that parameter's se is unbounded
    lam, vec = np.linalg.eig(np.eye(p) - Dinv @ d_w)
    root = np.where(lam.real > LEVERAGE_FLOOR, lam, LEVERAGE_FLOOR) ** -0.5
    u = (vec @ (root[:, :, None] * np.linalg.solve(vec, (s_w @ Dinv.T)[:, :, None])))[:, :, 0].real
    se = np.sqrt(np.sum(u**2, axis=0) / per)
    B = u[::per]
    dof = np.clip(1.5 * 3 * np.sum(B**2, axis=0) ** 2 / np.maximum(np.sum(B**4, axis=0), 1e-300), 1, None)
    t = stats.t.ppf(0.975, dof)
    return [(float(c - k * e), float(c + k * e)) for c, k, e in zip(theta, t, se)]


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
        rel = _quant_rel(data, q)
        atten = _quant_attenuation(data)
        m_lo, m_hi = res.ci95["m"]
        if rel > QUANT_NOISE_REL:
            flags.append(f"quantised-position: encoder step {q:.3g} m makes x'' noise {100 * rel:.1f} % "
                         f"of its signal (m {'corrected for ' if method == 'l2' else 'biased low by '}"
                         f"~{100 * atten:.2g} %, a white-noise model of the step that holds less the "
                         "larger it is); lower --cutoff or use more excitation")
        elif method == "l1" and atten * abs(res.m) > BIAS_SE * (m_hi - m_lo) / 3.92:
            flags.append(f"quantised-position: encoder step {q:.3g} m biases l1's m low by about "
                         f"{100 * atten:.2g} % or more, beyond half its standard error; l2 corrects it")
    stuck = _stuck_fraction(data, q or 0.0)
    if stuck > STICK_FRACTION:
        flags.append(f"stick-slip: the handle is at rest under a nonzero force for {100 * stuck:.0f} % "
                     "of the samples; there the friction force is anything up to the Coulomb level, "
                     "f = m x'' + b x' + Fc sign(x') does not hold, and b and Coulomb may be biased "
                     "(b typically high): raise the excitation so the handle keeps moving")
    return flags


def _quant_rel(data: _Data, q: float) -> float:
    """Noise of x'' from an encoder step ``q`` (white, q^2 / 12), relative to its signal."""
    return q / np.sqrt(12) * data.a_noise_gain / max(float(np.std(data.cols["m"])), 1e-300)


def _quant_attenuation(data: _Data) -> float:
    """Least squares' attenuation of m by the encoder's step (module doc); 0 without one."""
    q = position_quantum(data.x)
    rel = _quant_rel(data, q) if q else 0.0
    return rel**2 / (1 + rel**2)


def _stuck_fraction(data: _Data, q: float) -> float:
    """Fraction of samples at rest (|x'| below the velocity noise that the encoder step
    q leaves after the derivative filter) while the force is not near zero.

    A stuck handle (|f| <= Fc, x' = 0) breaks the sliding-friction model: the
    friction force is then whatever balances f, not Fc sign(x'). On a position that is
    not on an encoder grid, a sample whose raw position equals both neighbours' is at rest
    too (the filtered velocity blurs a stick: a 0.15 N chirp against 0.1 N of friction,
    20 % of its samples stuck, read as 2.8 %).
    """
    v = data.cols["b"]
    v_rest = max(REST_SIGMAS * q / np.sqrt(12) * data.v_noise_gain, REST_REL * float(np.std(v)))
    rest = np.abs(v) < v_rest
    if not q:
        dx = np.diff(data.x)
        rest[1:-1] |= (dx[:-1] == 0) & (dx[1:] == 0)
    pushed = np.abs(data.y) > STICK_FORCE_REL * np.sqrt(np.mean(data.y**2))
    return float(np.mean(rest & pushed))


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
