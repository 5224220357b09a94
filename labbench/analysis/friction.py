"""Friction in a measured closed-loop impedance: the friction-aware prediction of the
rendered K and B at the run's own excitation, the rule that picks the model the readout
compares against, and the verdict on that comparison.

**Prediction.** The device's Coulomb friction Fc (``labbench.model.device_friction``: given, a
chirp-ID's, the simulator's own; otherwise ``estimate``d from this record) acts as the
damper b_eq of ``labbench.model.friction.linearise`` under the recorded excitation; the
rendered K and B of the loop with b + b_eq are read off its exact sampled Z over the
same frequencies as the measurement's (``labbench.analysis.rendered.fit``). Beside it:
the velocity the record shows (zero-phase filtered differences, the identification's
cut-off rule, ``labbench.analysis.derivatives``), its rms against the linearisation's,
and Booton's form on it, Fc E|v| / E[v^2], which needs no Gaussian velocity.

**Which model the readout compares against** (``RULE``): the simplest the measurement
cannot tell from the richer one. The linear theory, unless the friction-aware prediction
differs from it by more than half a standard error of the measured K or B (the 95 %
half-width / 1.96; ``labbench.readout.verdict.BIAS_SE``: a shift that small leaves a 95 % interval
covering at least 91 %, so the linear theory is as good a reading); then the friction-aware
one. Decided from the predictions and the interval's width, never from where the measured
value fell. (A first rule, the whole half-width, compared the linear theory where friction
shifted B by up to a half-width: the K = 200 runs of the grid missed it at Fc 0.02 N.)

**Verdict** (``judge``; what an ``ok`` promises, ``labbench.readout.verdict.holds``): the
compared model's K and B inside the measured 95 % intervals: ok; outside 95 % but inside
99.9 % (``labbench.readout.verdict.VOUCH_STRETCH``): ok with a note saying so (never a bare
``ok`` beside a miss); beyond: doubtful, naming the likely cause with the number that
shows it: Coulomb friction the record's own closed-loop identification finds (its
cross-validated model selection, ``labbench.analysis.identify``), a velocity far from the
linearisation's (sticking), or the encoder step.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from labbench.readout import verdict
from labbench.analysis.dataio import Recording, position_quantum
from labbench.analysis.derivatives import default_cutoff, differentiate, force_band
from labbench.analysis.rendered import Z95
from labbench.model.device_friction import DeviceFriction
from labbench.model import friction as model
from labbench.model.ve import Plant, VirtualEnvironment

RULE = ("the simplest model the measurement cannot tell from the richer one: the linear "
        "theory unless the friction-aware one differs from it by more than half a standard error "
        "of the measured K or B")
# The linearisation assumes the velocity it predicts: a record whose velocity rms differs by
# more than this share is told so (sticking or a wrong Fc)
VELOCITY_MISMATCH = 0.1


@dataclass
class Prediction:
    """Friction's part in one record: the friction used (``friction``), the linearised loop
    (``linearised``; None without friction), b_eq at the ends of Fc's interval, the record's
    own velocity rms and Booton's form on it, and the record's own Coulomb estimate
    (``evidence``: an ``identify`` result's dict, or None when not made)."""

    friction: DeviceFriction
    linearised: model.Linearised | None
    b_eq_ci95: tuple[float, float] | None = None
    velocity_rms_measured: float | None = None
    b_eq_measured: float | None = None
    evidence: dict | None = None

    @property
    def plant(self) -> Plant | None:
        """The device with b + b_eq (None without friction or where it holds the handle)."""
        lin = self.linearised
        return lin.plant if lin is not None and lin.holds and lin.b_eq > 0 else None

    def as_dict(self) -> dict:
        lin = self.linearised
        return {**self.friction.as_dict(),
                "b_eq": None if lin is None or not lin.holds else lin.b_eq,
                "b_eq_ci95": None if self.b_eq_ci95 is None else list(self.b_eq_ci95),
                "velocity_rms": None if lin is None else lin.velocity_rms,
                "velocity_rms_measured": self.velocity_rms_measured,
                "b_eq_measured": self.b_eq_measured, "linearisation_holds": None if lin is None else lin.holds,
                "evidence": self.evidence}


def record_velocity(position, force, fs: float) -> np.ndarray:
    """The handle's velocity [m/s] from the sampled position: zero-phase low-pass and
    differences at the identification's cut-off (3x the force's band, at most 0.05 fs),
    which keeps an encoder step's noise out (``labbench.analysis.derivatives``)."""
    cut = default_cutoff(force_band(np.asarray(force, float), fs), fs)
    return differentiate(np.asarray(position, float), fs, cut).v


def estimate(rec: Recording, ve: VirtualEnvironment, latency: float = 0.0):
    """Fc from the record itself: the closed-loop identification (instrumental variables,
    ``labbench.analysis.compare.identify_closed_loop``) with the model chosen by
    cross-validation. Returns (DeviceFriction of origin ``record``, the identification);
    Fc = 0 when the selection keeps no Coulomb term.

    Fc is read from the part of the plant's force shaped as sign(x') in the time domain
    (beside m and b), not from the damping the ETFE reads, so the comparison still tests the
    linearisation: at 0.05 N the record's damping excess, read as a Gaussian b_eq, gives
    Fc 0.045 where this reads 0.049 (rough simulator, 30 s). Under white noise the sign is
    the expectation given the velocity the derivative filter leaves out
    (``labbench.analysis.identify``): without it Fc read 17 % low."""
    from labbench.analysis.compare import identify_closed_loop

    ident = identify_closed_loop(rec, ve, latency=latency, model="auto")
    fc = ident.params.get("coulomb")
    if fc is None:
        return DeviceFriction(0.0, None, "this record's closed-loop identification: no Coulomb "
                                         "term (" + _why(ident) + ")", "record"), ident
    lo, hi = ident.ci95["coulomb"]
    n = max(float(fc), 0.0)
    return DeviceFriction(n, (min(lo, n), max(hi, n)), "estimated from this record (closed-loop "
                          f"identification, {ident.verdict.level})", "record"), ident


def _why(ident) -> str:
    steps = [s for s in ident.selection.get("steps", []) if s.get("term") == "coulomb"]
    return steps[0]["why"] if steps else ident.selection.get("reason", "not selected")


def predict(plant: Plant, ve: VirtualEnvironment, friction: DeviceFriction, excitation, position,
            fs: float, latency: float = 0.0, evidence=None) -> Prediction:
    """Friction's part in the record of ``excitation`` and ``position`` (module doc), with
    Fc from ``friction`` (known: ``DeviceFriction.known``); ``evidence``: the record's own
    identification (``estimate``), when made."""
    v = record_velocity(position, excitation, fs)
    v_rms = float(np.sqrt(np.mean(v**2)))
    ev = _evidence(evidence)
    if not friction.known or friction.n == 0:
        return Prediction(friction, None, velocity_rms_measured=v_rms, evidence=ev)
    lin = model.linearise(plant, ve, friction.n, excitation, latency)
    ci = None
    if friction.ci95 is not None and lin.holds:
        ends = [model.linearise(plant, ve, max(x, 0.0), excitation, latency) for x in friction.ci95]
        ci = (ends[0].b_eq, ends[1].b_eq) if all(e.holds for e in ends) else None
    return Prediction(friction, lin, ci, v_rms, model.equivalent_damping(friction.n, v), ev)


def _evidence(ident) -> dict | None:
    if ident is None:
        return None
    fc = ident.params.get("coulomb")
    return {"model": ident.model, "coulomb_n": fc,
            "ci95": list(ident.ci95["coulomb"]) if fc is not None else None,
            "why": _why(ident), "level": ident.verdict.level}


def compared(rendered: dict, friction_fit) -> dict:
    """The model the readout compares against (``RULE``): ``{"model": "linear" | "friction",
    "K", "B", "rule"}`` from the rendered block (``rendered.rendered_impedance``) and the
    friction-aware fit over the same band (a ``rendered.LowFrequency``; None: no friction)."""
    th = rendered["theory"]
    if friction_fit is None:
        return {"model": "linear", "K": th["K"], "B": th["B"], "rule": RULE}
    se_k = (rendered["K_ci95"][1] - rendered["K_ci95"][0]) / 2 / Z95
    se_b = (rendered["B_ci95"][1] - rendered["B_ci95"][0]) / 2 / Z95
    apart = (abs(friction_fit.K - th["K"]) > verdict.BIAS_SE * se_k
             or abs(friction_fit.B - th["B"]) > verdict.BIAS_SE * se_b)
    if apart:
        return {"model": "friction", "K": friction_fit.K, "B": friction_fit.B, "rule": RULE}
    return {"model": "linear", "K": th["K"], "B": th["B"], "rule": RULE}


def compared_model(rendered: dict | None) -> str:
    """"friction" when the rendered block (``analyse``) is compared with the friction-aware
    theory, else "linear"."""
    cmp = (rendered or {}).get("compared") if isinstance(rendered, dict) else None
    return "friction" if isinstance(cmp, dict) and cmp.get("model") == "friction" else "linear"


def judge(rendered: dict, cmp: dict, pred: Prediction | None, quantum: float | None = None) -> verdict.Verdict:
    """The verdict on the compared model against the measured K and B (module doc)."""
    name = _model_name(cmp, pred)
    findings, notes = [], []
    for key, unit, label in (("K", "N/m", "stiffness"), ("B", "N s/m", "damping")):
        value, (lo, hi), want = rendered[key], rendered[f"{key}_ci95"], cmp[key]
        if lo <= want <= hi:
            continue
        far = not (value - verdict.VOUCH_STRETCH * (value - lo) <= want <= value + verdict.VOUCH_STRETCH * (hi - value))
        text = (f"the {name} {'misses' if far else 'lies outside the 95 % interval of'} the measured "
                f"{label}: {want:.4g} {unit} against {value:.4g} [{lo:.4g}, {hi:.4g}]")
        if far:
            findings.append((verdict.DOUBTFUL, f"{text}; {_cause(cmp, pred, quantum)}"))
        else:
            notes.append(f"{text} (within its 99.9 % interval)")
    lin = pred.linearised if pred is not None else None
    if lin is not None and lin.holds and cmp["model"] == "linear":
        notes.append(f"Coulomb friction {pred.friction.n:.2g} N acts as {lin.b_eq:.2g} N s/m "
                     "here, within what the measurement resolves")
    elif lin is not None and lin.holds:
        notes.append(f"the device is not linear: Coulomb friction {pred.friction.n:.2g} N acts as "
                     f"{lin.b_eq:.2g} N s/m at this run's {lin.velocity_rms:.2g} m/s rms, and as "
                     "less at a stronger excitation: this Z holds at this excitation only")
    measured = pred.velocity_rms_measured if pred is not None else None
    if lin is not None and lin.holds and not findings and measured \
            and abs(measured / lin.velocity_rms - 1) > VELOCITY_MISMATCH:  # (a miss's cause says it)
        notes.append(f"the handle moved at {measured:.2g} m/s rms where the linearisation has it at "
                     f"{lin.velocity_rms:.2g}: it sticks for part of the record, which the "
                     "linearisation leaves out")
    return verdict.judge(findings, notes=notes)


def _model_name(cmp: dict, pred: Prediction | None) -> str:
    if cmp["model"] == "friction" and pred is not None:
        return f"sampled theory with Coulomb friction {pred.friction.n:.2g} N"
    return "linear sampled theory"


def _cause(cmp: dict, pred: Prediction | None, quantum: float | None) -> str:
    """The likely cause of a miss, with the number that shows it (module doc)."""
    ev = pred.evidence if pred is not None else None
    found = ev is not None and ev.get("coulomb_n") is not None and ev["coulomb_n"] > 0
    if cmp["model"] == "linear":
        if found:
            beq = _beq_text(pred, ev["coulomb_n"])
            return (f"the response depends on amplitude: this record's closed-loop identification "
                    f"finds Coulomb friction {ev['coulomb_n']:.2g} N{beq}; give the device's friction "
                    "(plant_coulomb_n, a chirp-ID's) for the friction-aware theory")
    else:
        lin = pred.linearised
        measured = pred.velocity_rms_measured
        if measured and abs(measured / lin.velocity_rms - 1) > VELOCITY_MISMATCH:
            return (f"the handle moved at {measured:.2g} m/s rms where the linearisation predicts "
                    f"{lin.velocity_rms:.2g}: friction this strong against this excitation makes it "
                    "stick, which no damper does; raise the excitation")
        if pred.friction.origin == "record":
            lo, hi = pred.friction.interval
            return (f"the Coulomb level was estimated from this record ({pred.friction.n:.2g} N, "
                    f"[{lo:.2g}, {hi:.2g}]), which shares its noise: a chirp-ID measures it apart "
                    "(plant_coulomb_n)")
        if found and pred.friction.ci95 is not None and not (
                pred.friction.ci95[0] <= ev["coulomb_n"] <= pred.friction.ci95[1]):
            return (f"this record's own Coulomb estimate {ev['coulomb_n']:.2g} N differs from the "
                    f"{pred.friction.n:.2g} N used ({pred.friction.source})")
    if quantum:
        return (f"the encoder step ({quantum:.3g} m) or another nonlinearity; or a plant or delay "
                "the theory does not know (analyze etfe --fit measures them)")
    return "a plant, delay or nonlinearity the theory does not know (analyze etfe --fit measures m, b, delay)"


def _beq_text(pred: Prediction | None, fc: float) -> str:
    if pred is None or not pred.velocity_rms_measured:
        return ""
    beq = model.gaussian_equivalent_damping(fc, pred.velocity_rms_measured)
    return f", a damper of {beq:.2g} N s/m at this run's {pred.velocity_rms_measured:.2g} m/s rms"


def analyse(res, rendered: dict | None, plant: Plant, ve: VirtualEnvironment,
            friction: DeviceFriction, rec: Recording, latency: float = 0.0,
            evidence=None) -> tuple[Prediction, dict | None]:
    """Friction's part in one ETFE (module doc): (the ``Prediction``, whose ``as_dict`` is
    the results' ``friction`` block; the ``rendered`` block with ``friction`` (the friction-aware K, B), ``compared`` and
    ``verdict`` added; None when there is none). ``friction`` not known: estimated from
    ``rec`` (``estimate``); ``evidence``: the record's own identification when already
    made (else made where a miss needs its cause)."""
    from labbench.analysis import rendered as rendered_mod
    from labbench.model import linear

    if not friction.known:
        friction, evidence = estimate(rec, ve, latency)
    pred = predict(plant, ve, friction, rec.force, rec.position, rec.fs, latency, evidence)
    if rendered is None:
        return pred, None
    fit = None
    if pred.plant is not None:
        Zf = linear.z_sampled(pred.plant, ve, res.w, latency) if linear.whole_samples(ve) else \
            linear.z_paper(pred.plant, ve, res.w, latency)
        fit = rendered_mod.fit(res.w, Zf, where=tuple(rendered["band_rad_s"]))
    out = dict(rendered)
    if fit is not None:
        out["friction"] = {"K": fit.K, "B": fit.B, "coulomb_n": friction.n,
                           "b_eq": pred.linearised.b_eq, "velocity_rms": pred.linearised.velocity_rms}
    cmp = compared(rendered, fit)
    quantum = position_quantum(np.asarray(rec.position))
    judged = judge(rendered, cmp, pred, quantum)
    if judged.level != verdict.OK and pred.evidence is None:  # a miss: look for its cause
        pred.evidence = _evidence(estimate(rec, ve, latency)[1])
        judged = judge(rendered, cmp, pred, quantum)
    out["compared"] = cmp
    out["verdict"] = judged.as_dict()
    return pred, out


def fitted_b_eq(total: Plant, ve: VirtualEnvironment, coulomb_n: float, excitation,
                latency: float = 0.0) -> float:
    """Friction's equivalent damping inside a fitted plant whose b is the loop's whole
    damping at this excitation (``separate``): Fc sqrt(2 / pi) / sigma_v of that loop on
    the recorded ``excitation`` (0 for a plant without damping)."""
    if total.b <= 0 or coulomb_n <= 0:
        return 0.0
    return model.gaussian_equivalent_damping(coulomb_n, model.velocity_rms(total, ve, excitation, latency))


def separate(fit: dict, pred: Prediction, ve: VirtualEnvironment, excitation,
             resolution: float | None = None) -> dict:
    """The closed-loop fit (``labbench.analysis.loopfit``, as a dict) with friction's part
    of its b taken out where Fc is known (given, a chirp-ID's, the simulator's), else its
    verdict saying that b includes it (module doc of ``labbench.model.friction``: the ETFE
    sees b + b_eq).

    The fitted b is the loop's whole damping at this excitation, so b_eq follows from it
    directly: Fc sqrt(2 / pi) / sigma_v of the fitted loop (m, b, its delay) on the
    recorded excitation; ``b_viscous`` = b - b_eq. Its 95 % interval takes b's interval and
    Fc's (b_viscous rises with b and falls with Fc) and the two forms of b_eq, the Gaussian
    one and Booton's on the record's velocity (``Prediction.b_eq_measured`` scaled to the
    same loop): the linearisation's own uncertainty where the velocity is not Gaussian.
    ``resolution``: b's accuracy target [N s/m] below which friction's share is not worth a
    word (None: b's own interval)."""
    if "b" not in fit or "m" not in fit:
        return fit
    out = {**fit, "ci95": dict(fit["ci95"])}
    lo, hi = fit["ci95"]["b"]
    found = verdict.from_dict(fit.get("verdict")) or verdict.Verdict()
    reasons, notes, level = list(found.reasons), list(found.notes), found.level
    fr = pred.friction
    if fr.known and fr.n > 0 and fr.origin in ("given", "device"):
        latency = fit.get("td_s", 0.0)
        loop = ve.with_(td=_whole(fit.get("tv_s", ve.td), ve))

        def beq(total: float, fc: float) -> float:
            return fitted_b_eq(Plant(fit["m"], max(total, 0.0)), loop, fc, excitation, latency)

        b_eq = beq(fit["b"], fr.n)
        flo, fhi = fr.interval
        ratio = pred.b_eq_measured / pred.linearised.b_eq if pred.b_eq_measured and pred.linearised \
            and pred.linearised.holds and pred.linearised.b_eq > 0 else 1.0
        low = lo - max(beq(lo, fhi), beq(lo, fhi) * ratio)
        high = hi - min(beq(hi, max(flo, 0.0)), beq(hi, max(flo, 0.0)) * ratio)
        out.update(b_eq=b_eq, b_viscous=fit["b"] - b_eq)
        out["ci95"]["b_viscous"] = [max(low, 0.0), max(high, 0.0)]
        notes.append(f"b = {fit['b']:.3g} N s/m includes Coulomb friction {fr.n:.2g} N ({fr.source}) "
                     f"as {b_eq:.3g} N s/m at this excitation: the viscous b is {fit['b'] - b_eq:.3g} "
                     f"[{max(low, 0.0):.3g}, {max(high, 0.0):.3g}] N s/m")
    else:
        ev = pred.evidence
        fc = ev.get("coulomb_n") if ev else None
        if fc:
            share = model.gaussian_equivalent_damping(fc, pred.velocity_rms_measured or 0.0)
            if share > (resolution if resolution is not None else (hi - lo) / 2):
                level = max(level, verdict.DOUBTFUL, key=verdict.LEVELS.index)
                reasons.append(f"b includes Coulomb friction's equivalent damping, not only the "
                               f"device's viscous b: this record's own estimate Fc = {fc:.2g} N acts "
                               f"as ~{share:.2g} N s/m at {pred.velocity_rms_measured:.2g} m/s rms; "
                               "give the device's friction (a chirp-ID's) to separate them")
    out["verdict"] = verdict.Verdict(level, tuple(reasons), found.band, tuple(notes)).as_dict()
    return out


def _whole(tv: float, ve: VirtualEnvironment) -> float:
    """The fit's VE-path delay as the VE's td where it is whole samples (the fit's model)."""
    n = round(tv / ve.T)
    return n * ve.T if abs(tv / ve.T - n) < 0.01 else ve.td


# ----------------------------------------------------------------------------- excitation
SHARE = 0.1  # the pre-check's limit: friction's equivalent damping below this share of B + b


def plan(plant: Plant, ve: VirtualEnvironment, friction: DeviceFriction, excitation,
         latency: float = 0.0, force_limit_n: float | None = None) -> dict:
    """Before a white-noise ETFE, with the device's Coulomb friction known: the damper it will
    act as under the planned ``excitation`` (``model.linearise``, the same prediction the
    analysis makes), its share of the damping B + b the VE should render, and the white noise
    that keeps that share below ``SHARE`` (``model.excitation_for``, over the excitation's
    band), in one sentence (``text``)."""
    f = np.asarray(excitation, float)
    std = float(np.std(f))
    lin = model.linearise(plant, ve, friction.n, f, latency)
    target = plant.b + ve.B
    need = model.excitation_for(plant, ve, friction.n, SHARE * target, latency=latency)
    head = f"Coulomb friction {friction.n:.2g} N ({friction.source})"
    if not lin.holds:
        text = (f"{head} holds the handle against this {std:.2g} N excitation: no damper stands for "
                f"it; {need:.2g} N of white noise keeps it below {100 * SHARE:g} % of B + b")
    else:
        share = lin.b_eq / target
        text = (f"{head} will act as {lin.b_eq:.2g} N s/m at this {std:.2g} N excitation, "
                f"{100 * share:.0f} % of B + b = {target:.3g} N s/m; {need:.2g} N of white noise keeps "
                f"it below {100 * SHARE:g} %")
    if force_limit_n is not None and need > force_limit_n:
        text += f", beyond the rig's force limit {force_limit_n:g} N: the ETFE measures friction too"
    return {"coulomb_n": friction.n, "source": friction.source, "std_n": std,
            "b_eq": lin.b_eq if lin.holds else None, "share_limit": SHARE,
            "std_for_share_n": need, "text": text}


def levels(rendered: list, stds) -> dict:
    """The rendered K and B at each excitation level (``rendered``: each level's rendered block,
    ``analyse``'s, None where too short) and the verdict on how they follow the amplitude:
    where two levels' damping differs beyond both intervals (the 95 % half-widths added in
    quadrature), the response depends on amplitude: a note naming the levels where the
    compared theory follows it at each (friction predicts b_eq falling as the excitation
    grows), doubtful where it does not, naming the likely cause."""
    rows = []
    for std, rd in zip(stds, rendered):
        if rd is None:
            rows.append({"std_n": std})
            continue
        cmp = rd.get("compared") or {}
        rows.append({"std_n": std, "K": rd["K"], "K_ci95": rd["K_ci95"], "B": rd["B"], "B_ci95": rd["B_ci95"],
                     "compared": cmp.get("model"), "K_theory": cmp.get("K"), "B_theory": cmp.get("B"),
                     "B_linear": rd["theory"]["B"], "B_friction": (rd.get("friction") or {}).get("B"),
                     "holds": bool(rd["K_ci95"][0] <= cmp.get("K", math.nan) <= rd["K_ci95"][1]
                                   and rd["B_ci95"][0] <= cmp.get("B", math.nan) <= rd["B_ci95"][1])})
    got = [r for r in rows if "B" in r]
    apart = []
    for i in range(len(got)):
        for j in range(i + 1, len(got)):
            a, b = got[i], got[j]
            half = math.hypot((a["B_ci95"][1] - a["B_ci95"][0]) / 2, (b["B_ci95"][1] - b["B_ci95"][0]) / 2)
            if abs(a["B"] - b["B"]) > half:
                apart.append((a, b))
    seen = ", ".join(f"{r['B']:.3g} [{r['B_ci95'][0]:.3g}, {r['B_ci95'][1]:.3g}] N s/m at {r['std_n']:g} N"
                     for r in got)
    if not apart:
        v = verdict.judge([], notes=[f"no dependence on amplitude resolved: damping {seen}"] if len(got) > 1 else [])
    elif all(r["holds"] for r in got) and any(r["compared"] == "friction" for r in got):
        v = verdict.judge([], notes=[
            f"the response depends on amplitude: damping {seen}, as Coulomb friction predicts ("
            + ", ".join(f"{r['B_friction'] or r['B_theory']:.3g}" for r in got) + " N s/m)"])
    else:
        v = verdict.judge([(verdict.DOUBTFUL, f"the response depends on amplitude: damping {seen}; the "
                            "compared theory does not follow it ("
                            + ", ".join(f"{r['B_theory']:.3g}" for r in got) + " N s/m): damping that falls "
                            "as the excitation grows is Coulomb friction's mark (b_eq ~ Fc / sigma_v); give "
                            "the device's friction (a chirp-ID's)")])
    return {"levels": rows, "verdict": v.as_dict()}
