"""What a person reads of a run's results: the one source of the CLI's text and JSON, the
report's page 1 and the window (issue 30: the three said different things of one session).

``of_results(protocol, results, start)`` turns a run's results (the stop record's, or a
protocol's analysis of a session) into a ``Readout``: the verdicts, each with the band it
speaks of (``labbench.readout.verdict``); the stiffness and damping the display rendered beside the
commanded ones and the exact sampled theory's (``labbench.analysis.rendered``); the device
model the theory used and where it came from, in one phrase; and the summary numbers in
order, each a ``Value`` written by the one formatter (``labbench.readout.numfmt``). Every surface
writes these texts; none composes its own.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from labbench.readout.numfmt import band_text, digits_beside, fmt, fmt_ci, frequencies_in, frequency_text
from labbench.readout.verdict import FAILED, OK, Verdict, from_dict, worst
from labbench.scales import is_number

NAMES = {"etfe": "ETFE", "loop_fit": "closed-loop fit", "rendered": "against the theory",
         "levels": "amplitude"}


@dataclass(frozen=True)
class Value:
    """A number as read: SI ``value`` [``unit``], its 95 % interval ``lo``-``hi`` when it has
    one, ``quantity`` = "frequency" when display units convert it, and ``scale``: the size
    against which its interval's narrowness is judged (``numfmt.fmt_ci``; None: itself)."""

    value: float | None
    lo: float | None = None
    hi: float | None = None
    unit: str = ""
    quantity: str = ""
    scale: float | None = None
    digits: int = 4  # significant digits without an interval (numfmt.digits_beside)

    def text(self, units=None) -> str:
        if self.quantity == "frequency" and units is not None:
            conv = units.frequency_of
            return fmt_ci(conv(self.value), conv(self.lo), conv(self.hi), units.frequency,
                          None if self.scale is None else conv(self.scale), self.digits)
        return fmt_ci(self.value, self.lo, self.hi, self.unit, self.scale, self.digits)

    def as_dict(self) -> dict:
        d = {"value": self.value, "unit": self.unit}
        if self.lo is not None and self.hi is not None:
            d["ci95"] = [self.lo, self.hi]
        return d


@dataclass(frozen=True)
class Judged:
    """A verdict and what it judges ("ETFE", "identification (l2)", "delay", ...)."""

    what: str
    verdict: Verdict

    def line(self, units=None) -> str:
        return f"{self.what}: {self.verdict.line(units)}"

    def as_dict(self, units=None) -> dict:
        return {"what": self.what, **self.verdict.as_dict(), "line": self.line(units)}


@dataclass(frozen=True)
class Rendered:
    """The rendered stiffness ES(0) and damping ED(0) (device b included) with their
    intervals, read over ``band`` [rad/s]; commanded K, B and the device's b; the exact
    sampled theory's prediction (the same fit to its curve, and its true limit); with the
    device's Coulomb friction, the friction-aware prediction (``K_friction``, ``B_friction``,
    ``friction``: what it used, in words) and which of the two the result is compared with
    (``compared``: "linear" or "friction", ``labbench.analysis.friction.RULE``)."""

    K: Value
    B: Value
    band: tuple[float, float]
    n_freq: int
    K_commanded: float
    B_commanded: float
    b: float
    K_theory: float
    B_theory: float
    K_limit: float
    B_limit: float
    model: str
    trust: Verdict | None = None  # the verdict of the ETFE they were read from
    K_friction: float | None = None
    B_friction: float | None = None
    friction: str = ""
    compared: str = "linear"

    def caveat(self) -> str:
        """What a headline of numbers the ETFE's verdict does not vouch for says first
        (issue 43: "renders K = 344 N/m (321 to 368)" headlined an uncalibrated estimate):
        ``doubtful (the paper's estimator; see the ETFE's verdict): ``; nothing when ok."""
        v = self.trust
        if v is None or v.level == OK:
            return ""
        why = v.reasons[0].split(":", 1)[0] if v.reasons else "no reason recorded"
        return f"{v.level}{', not to be used' if v.level == FAILED else ''} ({why}; see the ETFE's verdict): "

    def sentence(self, units=None) -> str:
        head = (f"{self.caveat()}renders K = {self.K.text(units)} and damping {self.B.text(units)} "
                f"(b included) over {band_text(self.band, units)}; commanded K = {fmt(self.K_commanded)} "
                f"N/m, B + b = {fmt(self.B_commanded + self.b)} N s/m; ")
        linear = f"{fmt(self.K_theory)} N/m, {fmt(self.B_theory)} N s/m"
        if self.B_friction is None:
            return head + f"{self.model} theory {linear}"
        with_friction = (f"{self.model} theory with {self.friction}: {fmt(self.K_friction)} N/m, "
                         f"{fmt(self.B_friction)} N s/m")
        if self.compared == "friction":
            return head + f"compared with the {with_friction}; linear: {linear}"
        return head + (f"compared with the linear {self.model} theory {linear} (the "
                       f"{with_friction}: not told apart by this measurement)")

    def as_dict(self, units=None) -> dict:
        return {"K": self.K.as_dict(), "B": self.B.as_dict(), "band_rad_s": list(self.band),
                "n_freq": self.n_freq, "level": OK if self.trust is None else self.trust.level,
                "commanded": {"K": self.K_commanded, "B": self.B_commanded,
                                                     "b": self.b},
                "theory": {"model": self.model, "K": self.K_theory, "B": self.B_theory,
                           "K_limit": self.K_limit, "B_limit": self.B_limit},
                "friction": None if self.B_friction is None else {
                    "K": self.K_friction, "B": self.B_friction, "text": self.friction},
                "compared": self.compared, "sentence": self.sentence(units)}


@dataclass(frozen=True)
class PlantSource:
    """The device model a run's theory used and where it came from, in one phrase."""

    m: float
    b: float
    source: str

    def text(self) -> str:
        return f"m = {fmt(self.m)} kg, b = {fmt(self.b)} N s/m ({self.source})"


@dataclass
class Readout:
    """What a person reads of one result (module doc)."""

    protocol: str
    title: str = ""
    verdicts: list[Judged] = field(default_factory=list)
    # (label, what is read): a Value, words, or (name, Value) pairs read as "m = ...; b = ..."
    rows: list[tuple[str, Value | str | tuple]] = field(default_factory=list)
    rendered: Rendered | None = None
    plant: PlantSource | None = None
    # labels of the rows a one-page summary keeps (None: all); the rest are details
    headline: tuple[str, ...] | None = None

    @property
    def verdict(self) -> Verdict:
        """All verdicts as one: the worst level, every reason."""
        return worst(j.verdict for j in self.verdicts)

    def row_texts(self, units=None) -> list[tuple[str, str]]:
        return [(label, _text(v, units)) for label, v in self.rows]

    def text_lines(self, units=None) -> list[str]:
        """The CLI's summary: the rendered impedance first, then the rows, then the verdicts
        (a verdict of the same name as a row is written on the row: "delay: ok; 0.9 ...")."""
        lines = [self.rendered.sentence(units)] if self.rendered is not None else []
        own = {j.what: j for j in self.verdicts}
        for label, text in self.row_texts(units):
            j = own.pop(label, None)
            lines.append(f"{label}: {text}" if j is None else f"{j.line(units)}; {text}")
        lines += [j.line(units) for j in self.verdicts if j.what in own]
        return lines

    def as_dict(self, units=None) -> dict:
        return {"protocol": self.protocol, "title": self.title,
                "verdicts": [j.as_dict(units) for j in self.verdicts],
                "rows": [{"label": label, "text": text, **_row_dict(v)}
                         for (label, v), (_, text) in zip(self.rows, self.row_texts(units))],
                "rendered": None if self.rendered is None else self.rendered.as_dict(units),
                "plant": None if self.plant is None else {
                    "m": self.plant.m, "b": self.plant.b, "source": self.plant.source,
                    "text": self.plant.text()}}


def _text(v, units=None) -> str:
    if isinstance(v, Value):
        return v.text(units)
    if isinstance(v, tuple):
        return "; ".join(f"{name} = {x.text(units)}" for name, x in v)
    return frequencies_in(str(v), units)


def _row_dict(v) -> dict:
    if isinstance(v, Value):
        return v.as_dict()
    if isinstance(v, tuple):
        return {"parts": {name: x.as_dict() for name, x in v}}
    return {}


# ----------------------------------------------------------------------------- entry points
def of_results(protocol: str, results: dict | None, start: dict | None = None) -> Readout:
    """The readout of a run's ``results`` (module doc); ``start``: its start record (the
    VE, the rig, where the plant came from). Results read from a file are not trusted: what
    is missing or malformed is left out."""
    results = results if isinstance(results, dict) else {}
    start = start if isinstance(start, dict) else {}
    if results.get("error"):
        return Readout(protocol, "Analysis failed", rows=[("error", str(results["error"]))])
    if isinstance(results.get("etfe"), dict):
        return _etfe(protocol, results, start)
    if isinstance(results.get("identification"), dict):
        return _identification(protocol, results)
    if protocol == "commission" or isinstance(results.get("changes"), dict):
        return _commission(protocol, results)
    if "measured_boundary" in results:
        return _stability(protocol, results)
    return Readout(protocol)


def of_etfe_analysis(d: dict, start: dict | None = None) -> Readout:
    """The readout of ``labbench analyze etfe``'s result (``FrequencyResponse.as_dict``)."""
    theory = d.get("theory") if isinstance(d.get("theory"), dict) else {}
    results = {"etfe": d, "loop_fit": d.get("fit"), "rendered": d.get("rendered"),
               "plant": theory.get("plant"), "friction": d.get("friction"),
               "deviation_vs_sampled": _deviation_of_analysis(d),
               "deviation_vs_friction": theory.get("friction"), "bandwidths": d.get("bandwidths")}
    source = (d.get("theory") or {}).get("plant_source")
    return _etfe("etfe", results, start or {}, source if isinstance(source, str) else None)


def of_identification(d: dict, method: str | None = None) -> Readout:
    """The readout of ``labbench analyze id``'s result (``IdResult.as_dict``)."""
    return _identification("chirp-id", {"identification": {method or d.get("method") or "fit": d}})


# ----------------------------------------------------------------------------- plant source
def plant_source(start: dict) -> str:
    """Where the plant of a run's theory came from, in one phrase (its start record)."""
    found = start.get("plant_from") if isinstance(start.get("plant_from"), dict) else {}
    if isinstance(found.get("session"), str):
        return f"identified in {session_label(found['session'])}"
    if found.get("nominal") is True:  # a campaign's point that ran the rig's nominal model
        return "the rig's nominal model"
    config = start.get("protocol") if isinstance(start.get("protocol"), dict) else {}
    if config.get("plant_m_kg") is not None and config.get("plant_b") is not None:
        return "given in the run's settings"
    return "the rig's nominal model"


def session_label(path) -> str:
    """A session's file name less its uid: ``20261203-063850_chirp-id`` (when and what)."""
    return Path(str(path)).stem.rsplit("_", 1)[0]


# ----------------------------------------------------------------------------- per result
def _num(x) -> float | None:
    return float(x) if is_number(x) else None


def _band(x) -> list[float] | None:
    """A recorded band [low, high] rad/s; None unless it is two numbers."""
    both = [_num(v) for v in x] if isinstance(x, list) and len(x) == 2 else [None]
    return None if None in both else both


def _ci(d: dict, key: str) -> tuple[float | None, float | None]:
    ci = (d.get("ci95") or {}).get(key) if isinstance(d.get("ci95"), dict) else None
    if isinstance(ci, (list, tuple)) and len(ci) == 2:
        return _num(ci[0]), _num(ci[1])
    return None, None


def _judged(what: str, d) -> list[Judged]:
    v = from_dict(d.get("verdict")) if isinstance(d, dict) else None
    return [] if v is None else [Judged(what, v)]


def _etfe(protocol: str, results: dict, start: dict, source: str | None = None) -> Readout:
    e = results["etfe"]
    r = Readout(protocol, "Rendered impedance against the exact sampled theory",
                headline=("|Z - Z_theory| / |Z_theory|", "friction", "w_s*", "w_b*",
                          "device model of the theory"))
    r.verdicts = (_judged(NAMES["etfe"], e) + _judged(NAMES["rendered"], results.get("rendered"))
                  + _judged(NAMES["levels"], results.get("levels"))
                  + _judged(NAMES["loop_fit"], results.get("loop_fit")))
    plant = results.get("plant") if isinstance(results.get("plant"), dict) else {}
    m, b = _num(plant.get("m")), _num(plant.get("b"))
    if m is not None and b is not None:
        r.plant = PlantSource(m, b, source or plant_source(start))
    fr = results.get("friction") if isinstance(results.get("friction"), dict) else {}
    r.rendered = _rendered(results.get("rendered"), from_dict(e.get("verdict")),
                           friction_text(fr, start))
    compared = r.rendered.compared if r.rendered is not None else "linear"
    dev = results.get("deviation_vs_friction") if compared == "friction" else None
    against = " (against the friction-aware theory)" if isinstance(dev, dict) else ""
    dev = dev if isinstance(dev, dict) else results.get("deviation_vs_sampled")
    dev = dev if isinstance(dev, dict) else {}
    band = _band(dev.get("band_rad_s"))
    if _num(dev.get("median_rel")) is not None and band is not None:
        r.rows.append(("|Z - Z_theory| / |Z_theory|", f"median {_pct(dev['median_rel'])}, max "
                       f"{_pct(dev.get('max_rel'))}{_where_max(dev)} over {band_text(band)}{against}"))
    if _num(fr.get("n")) is not None:
        r.rows.append(("friction", _friction_row(fr, start)))
    plan = (start.get("precheck") or {}).get("friction") if isinstance(start.get("precheck"), dict) else None
    if isinstance(plan, dict) and isinstance(plan.get("text"), str):
        r.rows.append(("excitation", plan["text"]))
    levels = results.get("levels") if isinstance(results.get("levels"), dict) else {}
    for row in levels.get("levels") or []:
        if isinstance(row, dict) and _num(row.get("std_n")) is not None and _num(row.get("B")) is not None:
            r.rows.append((f"at {fmt(row['std_n'])} N", _level_text(row)))
    bw = results.get("bandwidths") if isinstance(results.get("bandwidths"), dict) else {}
    for sym, key in (("w_s*", "ws_star"), ("w_b*", "wb_star")):
        got, want = _num(bw.get(f"{key}_measured")), _num(bw.get(f"{key}_predicted"))
        if got is not None or want is not None:
            r.rows.append((sym, (("measured", Value(got, unit="rad/s", quantity="frequency")),
                                 ("sampled theory", Value(want, unit="rad/s", quantity="frequency")))))
    if r.plant is not None:
        r.rows.append(("device model of the theory", r.plant.text()))
    fit = results.get("loop_fit") if isinstance(results.get("loop_fit"), dict) else {}
    if "m" in fit:
        r.rows.append(("closed-loop fit", _fit_parts(fit)))
    elif fit.get("error"):
        r.rows.append(("closed-loop fit", f"none: {fit['error']}"))
    return r


def _rendered(d, trust: Verdict | None = None, friction: str = "") -> Rendered | None:
    if not isinstance(d, dict):
        return None
    th = d.get("theory") if isinstance(d.get("theory"), dict) else {}
    cmd = d.get("commanded") if isinstance(d.get("commanded"), dict) else {}
    K, B = _num(d.get("K")), _num(d.get("B"))
    band = _band(d.get("band_rad_s"))
    nums = [_num(x) for x in (cmd.get("K"), cmd.get("B"), cmd.get("b"), th.get("K"), th.get("B"),
                              th.get("K_limit"), th.get("B_limit"))]
    if K is None or B is None or None in nums or band is None:
        return None
    (klo, khi), (blo, bhi) = _pair(d.get("K_ci95")), _pair(d.get("B_ci95"))
    fr = d.get("friction") if isinstance(d.get("friction"), dict) else {}
    kf, bf = _num(fr.get("K")), _num(fr.get("B"))
    with_friction = kf is not None and bf is not None
    compared = d.get("compared") if isinstance(d.get("compared"), dict) else {}
    return Rendered(Value(K, klo, khi, "N/m", scale=max(abs(nums[0]), abs(K))),
                    Value(B, blo, bhi, "N s/m", scale=max(abs(nums[1] + nums[2]), abs(B))),
                    (float(band[0]), float(band[1])), int(d.get("n_freq") or 0), *nums,
                    str(th.get("model") or "sampled"), trust, kf if with_friction else None,
                    bf if with_friction else None, friction if with_friction else "",
                    "friction" if with_friction and compared.get("model") == "friction" else "linear")


def friction_source(fr: dict, start: dict) -> str:
    """Where a run's Coulomb friction came from, in one phrase: the chirp-ID session its
    plant came from when that gave it (the start record's ``plant_from``), else as recorded."""
    found = start.get("plant_from") if isinstance(start.get("plant_from"), dict) else {}
    if fr.get("origin") == "given" and isinstance(found.get("session"), str) \
            and _num(found.get("coulomb_n")) is not None:
        return f"identified in {session_label(found['session'])}"
    return str(fr.get("source") or fr.get("origin") or "as recorded")


def friction_text(fr: dict, start: dict) -> str:
    """``Coulomb friction 0.020 N (chirp-ID ...) at this run's 0.029 m/s rms``; "" without one."""
    n, v = _num(fr.get("n")), _num(fr.get("velocity_rms"))
    if n is None:
        return ""
    at = f" at this run's {fmt(v, 2)} m/s rms" if v is not None else ""
    return f"Coulomb friction {fmt(n, 2)} N ({friction_source(fr, start)}){at}"


def _level_text(row: dict) -> str:
    """One excitation level's rendered K, B and the theory it is compared with."""
    (klo, khi), (blo, bhi) = _pair(row.get("K_ci95")), _pair(row.get("B_ci95"))
    theory = _num(row.get("B_theory"))
    said = "" if theory is None else (f"; {'friction-aware' if row.get('compared') == 'friction' else 'linear'}"
                                      f" theory {fmt(theory)} N s/m")
    return (f"K = {fmt_ci(row['K'], klo, khi, 'N/m')}, damping {fmt_ci(row['B'], blo, bhi, 'N s/m')}"
            f"{said}")


def _friction_row(fr: dict, start: dict) -> str:
    """The friction used and the damper it acts as: Fc [interval] (source); b_eq at the
    predicted velocity rms, with the model's range from Fc's interval (not a measurement's);
    the record's own velocity and Booton's form on it."""
    lo, hi = _pair(fr.get("ci95"))
    text = f"Fc = {fmt_ci(fr['n'], lo, hi, 'N')} ({friction_source(fr, start)})"
    beq, v, vm, bm = (_num(fr.get(k)) for k in ("b_eq", "velocity_rms", "velocity_rms_measured",
                                                 "b_eq_measured"))
    if fr.get("linearisation_holds") is False:
        return text + ": no damper stands for it (friction holds the handle against this excitation)"
    if beq is not None and v is not None:
        blo, bhi = _pair(fr.get("b_eq_ci95"))
        span = f" ({fmt(blo, 3)} to {fmt(bhi, 3)} from Fc's interval)" if blo is not None and bhi is not None else ""
        text += f": a damper of {fmt(beq, 3)} N s/m{span} at {fmt(v, 3)} m/s rms (statistical linearisation)"
    if vm is not None and bm is not None:
        text += f"; the record's velocity {fmt(vm, 3)} m/s rms, Fc E|v|/E[v^2] = {fmt(bm, 3)} N s/m"
    return text


def _pair(x) -> tuple[float | None, float | None]:
    if isinstance(x, (list, tuple)) and len(x) == 2:
        return _num(x[0]), _num(x[1])
    return None, None


def _fit_parts(fit: dict) -> tuple:
    """The loop fit's m, b (and the viscous b where friction's part was taken out) and delays
    (device td, VE-path tv; in ms, judged against 1 ms)."""
    parts = [("m", Value(_num(fit.get("m")), *_ci(fit, "m"), "kg")),
             ("b", Value(_num(fit.get("b")), *_ci(fit, "b"), "N s/m"))]
    if _num(fit.get("b_viscous")) is not None:  # friction's part of b taken out (analysis.friction)
        parts.append(("viscous b", Value(fit["b_viscous"], *_ci(fit, "b_viscous"), "N s/m")))
    for key, name in (("td_s", "td"), ("tv_s", "tv")):
        if _num(fit.get(key)) is not None and None not in _ci(fit, key):
            lo, hi = _ci(fit, key)
            parts.append((name, Value(1e3 * fit[key], None if lo is None else 1e3 * lo,
                                      None if hi is None else 1e3 * hi, "ms", scale=1.0)))
    return tuple(parts)


def _deviation_of_analysis(d: dict) -> dict:
    th = d.get("theory") if isinstance(d.get("theory"), dict) else {}
    return {"band_rad_s": th.get("band_rad_s"), "median_rel": th.get("deviation_median"),
            "max_rel": th.get("deviation_max"), "max_rad_s": th.get("deviation_max_rad_s"),
            "max_band_rel": th.get("deviation_max_band_rel")}


def _where_max(dev: dict) -> str:
    """`` at 42.7 rad/s (95 % band there 2.1 %)``: a large max beside an ``ok`` verdict reads
    against its own frequency's noise; nothing for a record that does not say (older sessions)."""
    w, band = _num(dev.get("max_rad_s")), _num(dev.get("max_band_rel"))
    if w is None or band is None:
        return ""
    return f" at {frequency_text(w)} (95 % band there {_pct(band)})"


def _identification(protocol: str, results: dict) -> Readout:
    """The primary fit (l2 when there is one) in full; the others as cross-checks."""
    r = Readout(protocol, "Identified device",
                headline=("model", "mass m", "damping b", "Coulomb friction Fc", "force offset f0"))
    fits = {k: v for k, v in results["identification"].items() if isinstance(v, dict)}
    if not fits:
        return r
    primary = "l2" if "l2" in fits else next(iter(fits))
    fit = fits[primary]
    r.rows.append(("model", f"{_model_text(fit.get('model'))} ({primary} fit)"))
    r.rows.append(("mass m", Value(_num(fit.get("m")), *_ci(fit, "m"), "kg")))
    r.rows.append(("damping b", Value(_num(fit.get("b")), *_ci(fit, "b"), "N s/m", scale=_b_scale(fit))))
    for key, name in (("coulomb", "Coulomb friction Fc"), ("offset", "force offset f0")):
        if _num(fit.get(key)) is not None:
            r.rows.append((name, Value(fit[key], *_ci(fit, key), "N", scale=_force_scale(fit))))
    for method, other in fits.items():
        if method != primary:
            r.rows.append((f"cross-check: {method} fit",
                           (("m", Value(_num(other.get("m")), *_ci(other, "m"), "kg")),
                            ("b", Value(_num(other.get("b")), *_ci(other, "b"), "N s/m",
                                        scale=_b_scale(other))))))
    for method, f in fits.items():
        r.verdicts += _judged(f"identification ({method})", f)
    return r


def _b_scale(fit: dict) -> float | None:
    """b's scale: the force's, per unit velocity (b near 0 is exact only against that)."""
    m, b = _num(fit.get("m")), _num(fit.get("b"))
    return None if m is None or b is None else max(abs(b), 1e-3 * abs(m))


def _force_scale(fit: dict) -> float | None:
    rms = _num(fit.get("rms_residual"))
    return None if rms is None else max(rms, 1e-3)


def _model_text(model) -> str:
    return {"mb": "f = m x'' + b x'", "mbc": "f = m x'' + b x' + Fc sign(x')",
            "mbco": "f = m x'' + b x' + Fc sign(x') + f0"}.get(model, str(model))


CHECKS = ("direction", "delay", "scale", "friction", "k_max")


def _commission(protocol: str, results: dict) -> Readout:
    r = Readout(protocol, "Commissioning")
    d = results.get("direction") if isinstance(results.get("direction"), dict) else {}
    dl = results.get("delay") if isinstance(results.get("delay"), dict) else {}
    s = results.get("scale") if isinstance(results.get("scale"), dict) else {}
    fr = results.get("friction") if isinstance(results.get("friction"), dict) else {}
    k = results.get("k_max") if isinstance(results.get("k_max"), dict) else {}
    ci = _pair(dl.get("delay_ci_samples"))
    terms = ", ".join(f"{name} = {fmt(fr[key])} N" for name, key in (("Fc", "coulomb_n"), ("f0", "offset_n"))
                      if _num(fr.get(key)) is not None)
    r.rows = [
        ("direction", f"{d.get('agree')} of {d.get('of')} pulses moved with the force"),
        ("delay", Value(_num(dl.get("delay_samples")), *ci, "samples", scale=1.0)),
        ("scale", f"m = {fmt(s.get('m'), 5)} kg ({fmt(s.get('m_ratio'), 4)} x nominal), "
                  f"b = {fmt(s.get('b'), 5)} N s/m"),
        ("friction", f"model {fr.get('model')}" + (f", {terms}" if terms else
                                                    ": no Coulomb friction or offset")),
        ("k_max", f"{fmt(k.get('k_max_n_m'), 5)} N/m for a pure spring, B = 0 "
                  "(exact sampled, measured m, b, delay)"),
    ]
    changes = results.get("changes") if isinstance(results.get("changes"), dict) else {}
    r.rows.append(("rig changes", ", ".join(f"{key} = {v}" for key, v in changes.items()) or "none"))
    for check in CHECKS:
        r.verdicts += _judged(check, results.get(check))
    return r


def check_text(readout: Readout, check: str, units=None) -> str:
    """The numbers of one commissioning check, as every surface writes them."""
    return dict(readout.row_texts(units)).get(check, "-")


def _stability(protocol: str, results: dict) -> Readout:
    """The measured boundary against the exact sampled one and the paper's; with the device's
    friction known, the friction-aware boundary at the probe's swing and the measurement
    against it (``protocols/stability_probe.py``'s ``friction``); where the probe stopped
    and why (its ``stopped``; a one-page summary keeps it where no boundary was measured: there
    it is the reason)."""
    fr_label = "boundary (K), with friction at the probe's swing"
    none = _num(results.get("measured_boundary")) is None
    r = Readout(protocol, "Stability boundary", headline=(
        "boundary (K), measured", "boundary (K), exact sampled", "boundary (td), measured",
        "boundary (td), exact sampled", "measured against exact", fr_label,
        "measured against friction-aware", *(("stopped",) if none else ())))
    var = results.get("variable")
    unit = "N/m" if var == "K" else "s"
    steps = results.get("steps") if isinstance(results.get("steps"), list) else []
    r.rows.append(("probed variable", f"{var} ({unit}), {len(steps)} steps"))
    lo, hi = _pair(results.get("measured_ci95"))
    measured = _num(results.get("measured_boundary"))
    for label, key in (("measured", "measured_boundary"), ("exact sampled", "exact_boundary"),
                       ("paper's approximation", "approx_boundary")):
        x = _num(results.get(key))
        r.rows.append((f"boundary ({var}), {label}", Value(x, lo, hi, unit=unit) if key == "measured_boundary"
                       else Value(x, unit=unit, digits=digits_beside(measured, lo, hi, x))))
    rel = _num(results.get("rel_error_vs_exact"))
    if rel is not None:
        r.rows.append(("measured against exact", f"{100 * rel:+.2g} %"))
    fr = results.get("friction") if isinstance(results.get("friction"), dict) else {}
    k, (k_lo, k_hi), swing, fc = (_num(fr.get("k_max")), _pair(fr.get("k_range")),
                                  _num(fr.get("swing_m")), _num(fr.get("coulomb_n")))
    if k is not None and swing is not None and fc is not None:
        span = f" (range {k_lo:.4g} to {k_hi:.4g} over the steps' swings)" \
            if k_lo is not None and k_hi is not None else ""
        r.rows.append((fr_label, f"{k:.4g} N/m{span} at {1e3 * swing:.3g} mm; Coulomb "
                                 f"friction {fc:.3g} N"))
        rel = _num(fr.get("rel_error"))
        if rel is not None:
            agrees, tol = fr.get("agrees"), _num(fr.get("tolerance"))
            widened = f", widened by its {100 * tol:.2g} % tolerance," if tol else ""
            said = "" if not isinstance(agrees, bool) else \
                (f": {'agrees' if agrees else 'disagrees'} (the prediction's range{widened} "
                 f"{'meets' if agrees else 'misses'} the measured interval)")
            r.rows.append(("measured against friction-aware", f"{100 * rel:+.2g} %{said}"))
    if isinstance(results.get("stopped"), str):
        r.rows.append(("stopped", results["stopped"]))
    return r


def _pct(x) -> str:
    x = _num(x)
    return "-" if x is None else f"{100 * x:.2g} %"
