"""What a report says, in order: the summary (page 1), the details per session, and the
configuration in an appendix.

Page 1 answers a supervisor's questions: what ran, on which rig and device, and
the verdict (identified m and b with intervals and the model chosen; effective
impedances against the exact sampled theory in one figure, every ETFE session
overlaid; bandwidths measured against those the sampled theory predicts; the
stability margin; the loop delay, measured where known), then the flags with
what to do about them. Each protocol supplies its own part
(``ProtocolBase.report_sections``); the protocol classes are found by name
through ``labbench.registry``, never imported here.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from labbench.analysis.etfe import W_BAND
from labbench.errors import UserError
from labbench.readout.numfmt import band_text
from labbench.report.blocks import (
    Figure,
    Flag,
    Heading,
    Markup,
    PageBreak,
    Paragraph,
    ReportSections,
    Table,
    fmt,
    key_values,
    new_figure,
)
from labbench.report.session import ReportSession, load

# What to do about the analysis flags (labbench.analysis: the name before the colon).
FLAG_ACTIONS = {
    "short-record": "record longer (duration_s) before trusting the numbers",
    "wide-interval": "excite more (amplitude, band) or record longer",
    "force-outliers": "check the force sensor and cabling; compare with --method l1",
    "unmodelled-coulomb": "re-fit with the Coulomb term (--model mbc or auto)",
    "quantised-position": "use a finer encoder or more excitation; lower the derivative cut-off",
    "stick-slip": "raise the excitation so the handle keeps moving",
    "low-coherence": "trust only the band with coherence >= 0.8; raise std_n or record longer",
    "little-excitation": "widen the excitation band to cover these frequencies",
    "drift": "use the lpm estimator (the default), which removes record-edge leakage",
}
# Colours of the overlaid sessions (matplotlib's default cycle, by session order).
COLORS = [f"C{i}" for i in range(10)]

MAX_EVENT_ROWS = 100  # events listed and marked per session (a flood is counted)
MAX_TRIP_FLAGS = 10  # safety events named one by one among the flags


@dataclass
class Report:
    title: str
    subtitle: str
    blocks: list = field(default_factory=list)


def build(paths, warn=None) -> Report:
    """Load the sessions and lay out the whole report."""
    sessions = [load(p, index=i + 1, warn=warn) for i, p in enumerate(paths)]
    parts = [_sections(s) for s in sessions]
    title = "labbench report"
    rigs = sorted({s.rig_name for s in sessions})
    subtitle = (f"{len(sessions)} session{'s' * (len(sessions) > 1)} on rig "
                f"{', '.join(rigs)}; written {time.strftime('%Y-%m-%d %H:%M')}")
    blocks: list = [Heading("Summary", 1), *_summary(sessions, parts), PageBreak(),
                    Heading("Details", 1)]
    for s, part in zip(sessions, parts):
        blocks += ([PageBreak()] if s.index > 1 else []) + _details(s, part)
    blocks += [PageBreak(), Heading("Appendix: configuration", 1)]
    for s in sessions:
        blocks += _configuration(s)
    return Report(title, subtitle, blocks)


# ----------------------------------------------------------------------------- per protocol
def _sections(s: ReportSession) -> ReportSections:
    """The protocol's own part, or a flag saying why there is none."""
    from labbench.registry import protocol_class

    if not s.ch["t"].size or not s.results:
        return ReportSections(flags=[Flag(s.tag, "no results recorded (the run did not finish "
                                                 "its analysis)", "re-run the protocol")])
    if s.results.get("error"):
        return ReportSections(flags=[Flag(s.tag, f"analysis failed during the run: "
                                                 f"{s.results['error']}", "re-run the protocol")])
    try:
        cls = protocol_class(s.protocol)
        return cls(cls.Config.from_options(s.protocol, s.config)).report_sections(s)
    except UserError as exc:
        return ReportSections(flags=[Flag(s.tag, f"analysis for the report failed: {exc}",
                                          "check the session's protocol settings")])


# ----------------------------------------------------------------------------- summary
def _summary(sessions: list[ReportSession], parts: list[ReportSections]) -> list:
    from labbench.readout import wording

    blocks = [_what_ran(sessions)]
    # what each run found, in the words the CLI and the window use (labbench.readout.wording), then
    # the run's stability margin and loop delay (when it had a VE)
    reads = [wording.of_results(s.protocol, s.results, s.start) for s in sessions]
    verdicts = [(s, r.title, page_one_rows(r) + (_loop_rows(s, p.delay) if p.margin else []))
                for s, p, r in zip(sessions, parts, reads) if r.rows or r.verdicts]
    for title in dict.fromkeys(t for _, t, _ in verdicts):
        blocks.append(_column_table(title, [(s, rows) for s, t, rows in verdicts if t == title]))
    curves = [c for p in parts for c in p.curves]
    if curves:
        bands = [r.rendered.band for r in reads if r.rendered is not None]
        focus = (min(b[0] for b in bands), max(b[1] for b in bands)) if bands else W_BAND
        blocks.append(Figure(
            "Effective stiffness ES, damping ED and mass EM: measured (points) against the exact "
            "sampled theory (lines)" + (", one colour per session" if len(
                {c.color for c in curves}) > 1 else "") + f"; the damping axis shows "
            f"{band_text(focus)}, where the VE is meant to hold", _overlay(curves, focus)))
    blocks.append(_flags_table(sessions, parts, reads))
    return blocks


def page_one_rows(r) -> list[tuple[str, str]]:
    """A readout's rows on page 1: the rendered impedance, its headline numbers, every
    verdict (the rest of its rows open the session's details: ``readout_table``)."""
    rows = [("rendered", r.rendered.sentence())] if r.rendered is not None else []
    rows += [(label, text) for label, text in r.row_texts()
             if r.headline is None or label in r.headline]
    return rows + [(f"verdict: {j.what}", j.verdict.line()) for j in r.verdicts]


def readout_table(r) -> Table:
    """Every number of a readout, as the CLI prints them."""
    return Table(r.title or "Results", ["", ""], r.row_texts() + [
        (f"verdict: {j.what}", j.verdict.line()) for j in r.verdicts])


def _what_ran(sessions: list[ReportSession]) -> Table:
    rows = []
    for s in sessions:
        drops = f" ({s.dropped} dropped)" if s.dropped else ""
        rows.append([s.tag, s.protocol, s.started.replace("T", " ")[:19], fmt(s.duration_s, 3),
                     s.status, s.rig_name, s.device, f"{s.ch['t'].size}{drops}"])
    return Table("What ran", ["", "protocol", "started", "duration (s)", "status", "rig", "device",
                              "samples"], rows)


def _column_table(title: str, members) -> Table:
    """Rows = quantities, one value column per session (labels in the order first seen)."""
    labels = list(dict.fromkeys(label for _, rows in members for label, _ in rows))
    values = [dict(rows) for _, rows in members]
    header = [""] + [f"{s.tag} {s.protocol}" for s, _ in members]
    return Table(title, header, [[label] + [v.get(label, "-") for v in values]
                                 for label in labels])


def _loop_rows(s: ReportSession, measured_delay: str | None) -> list:
    """Stability margin of the run's VE from its precheck (exact sampled model) and the
    loop delay: as the protocol measured it, else the nominal one."""
    checks = (s.start.get("precheck") or {}).get("checks") or []
    rows = []
    for c in checks[:1]:  # the starting VE; every checked VE is listed in the appendix
        ve = c.get("ve") or {}
        K, km = ve.get("K") or 0.0, c.get("k_max")
        if ve.get("kind") in (None, "none"):
            continue
        margin = f" = {km / K:.3g} × K" if km and K > 0 else ""
        rows.append((Markup("K<sub>max</sub> (exact sampled)"),
                     f"{fmt(km)} N/m{margin}" if km else "no stable K"))
    if not rows:
        return rows
    ve = s.ve
    nominal = f"{1e3 * ve.td:g} ms" if ve is not None else "-"
    rows.append(("loop delay td", measured_delay or f"{nominal} nominal (not measured)"))
    return rows


def _overlay(curves, focus) -> object:
    from labbench.readout.figures import effective_figure

    return effective_figure(curves, focus=focus)


def _flags_table(sessions, parts, reads) -> Table | Paragraph:
    flags = [f for s, p, r in zip(sessions, parts, reads)
             for f in _run_flags(s) + p.flags + verdict_flags(s.tag, r)]
    if not flags:
        return Paragraph("No flags: every run completed with intact files, no dropped samples, "
                         "loop overruns or safety trips, and the analyses raised no warnings.")
    return Table("Flags and what to do", ["", "found", "what to do"],
                 [[f.session, f.problem, f.action] for f in flags])


def _run_flags(s: ReportSession) -> list[Flag]:
    out = []
    if s.status != "success":
        reason = (s.stop or {}).get("reason") or "no stop record"
        out.append(Flag(s.tag, f"run {s.status}: {reason}",
                        "read the events in the details; fix the cause and re-run"))
    if s.problem:
        out.append(Flag(s.tag, f"the file ends early ({s.problem}); everything before is shown",
                        "keep the file; re-run if the missing tail matters"))
    if s.malformed:
        out.append(Flag(s.tag, f"{len(s.malformed)} record field(s) of the wrong type left out: "
                               f"{'; '.join(s.malformed[:5])}",
                        "the session was written by a faulty or foreign tool; re-record it"))
    if s.dropped:
        out.append(Flag(s.tag, f"{s.dropped} samples dropped by the device link",
                        "check the bus load and the host's real-time set-up (docs/loop.md)"))
    if s.timing_problem:
        out.append(Flag(s.tag, s.timing_problem, "the host did not keep time (the overrun samples "
                        "are flagged in the record): grant real-time scheduling or unload the "
                        "machine (docs/loop.md), and re-run if the stalls matter"))
    trips = s.trips
    for e in trips[:MAX_TRIP_FLAGS]:
        out.append(Flag(s.tag, f"safety event {e.get('name')} at t = {fmt(e.get('t'))} s: "
                               f"{e.get('reason')}", "lower the gains or the excitation"))
    if len(trips) > MAX_TRIP_FLAGS:
        out.append(Flag(s.tag, f"{len(trips) - MAX_TRIP_FLAGS} more safety events",
                        "see the events table and the session file"))
    return out


def verdict_flags(tag: str, r) -> list[Flag]:
    """Every reason a readout's verdicts give (the doubts and failures over the band each
    speaks of, as the window and the CLI say them), with what to do about each."""
    out = []
    for j in r.verdicts:
        for text in j.verdict.reasons:
            name = text.split(":", 1)[0].strip()
            out.append(Flag(tag, f"{j.what} {j.verdict.level}: {text}",
                            FLAG_ACTIONS.get(name, "see docs/analysis.md")))
    return out


# ----------------------------------------------------------------------------- details
def _details(s: ReportSession, part: ReportSections) -> list:
    from labbench.readout import wording

    r = wording.of_results(s.protocol, s.results, s.start)
    blocks = [Heading(f"{s.tag} {s.protocol}: {s.path.name}", 2),
              *([readout_table(r)] if r.rows else []), *part.details]
    stop = s.stop or {}
    blocks.append(key_values("Run", [
        ("uid", str(s.start.get("uid") or "-")), ("started", s.started),
        ("software", str(s.start.get("software") or "-")),
        ("status", s.status), ("reason", str(stop.get("reason") or "-")),
        ("samples", s.ch["t"].size), ("duration (s)", s.duration_s),
        ("dropped samples", s.dropped), ("seed", _seed(s.start.get("seed"))),
        ("file damage", s.problem or "none")]))
    overview = _channels_figure(s)
    if overview:
        blocks.append(overview)
    rows = [[fmt(e.get("t")), str(e.get("name")), str(e.get("reason") or "")]
            for e in s.events[:MAX_EVENT_ROWS]]
    if len(s.events) > MAX_EVENT_ROWS:  # a flood is counted, not typeset
        rows.append(["...", f"{len(s.events) - MAX_EVENT_ROWS} more", "in the session file"])
    blocks.append(Table(f"Events ({len(s.events)})", ["t (s)", "event", "reason"], rows)
                  if rows else Paragraph("No events recorded."))
    blocks.append(_timing_table(s))
    return blocks


def _seed(seed) -> str:
    return "-" if seed is None else str(int(seed))


def _channels_figure(s: ReportSession) -> Figure | None:
    t = s.ch["t"]
    if t.size == 0:
        return None
    step = max(1, t.size // 20000)  # plenty of points for a page-wide plot
    sl = slice(None, None, step)
    fig = new_figure((7.2, 4.2))
    axes = fig.subplots(3, 1, sharex=True)
    axes[0].plot(t[sl], 1e3 * s.ch["position"][sl], lw=0.6)
    axes[0].set_ylabel("position (mm)", fontsize=8)
    axes[1].plot(t[sl], s.ch["velocity"][sl], lw=0.6)
    axes[1].set_ylabel("velocity (m/s)", fontsize=8)
    for name in ("excitation", "ve_force", "command"):
        axes[2].plot(t[sl], s.ch[name][sl], lw=0.6, label=name)
    axes[2].set_ylabel("force (N)", fontsize=8)
    axes[2].set_xlabel("time (s)", fontsize=8)
    axes[2].legend(fontsize=7, loc="upper right", ncols=3)
    for ax in axes:
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
        marks = [e["t"] for e in s.trips[:MAX_EVENT_ROWS] if e.get("t") is not None]
        if marks:  # one collection, not a line per event
            ax.vlines(marks, 0, 1, transform=ax.get_xaxis_transform(), color="r", lw=0.8,
                      alpha=0.6)
    return Figure("Recorded channels" + (" (red lines: safety events)" if s.trips else ""), fig)


def _timing_table(s: ReportSession) -> Table:
    from labbench.loop.timing import report_rows

    return key_values("Loop timing", report_rows((s.stop or {}).get("timing") or {}))


# ----------------------------------------------------------------------------- appendix
def _configuration(s: ReportSession) -> list:
    blocks = [Heading(f"{s.tag} {s.protocol}: {s.path.name}", 2),
              key_values(f"Protocol settings ({s.protocol})", list(s.config.items()))]
    rig = dict(s.start.get("rig") or {})
    sections = rig.pop("sections", {}) or {}
    items = list(rig.items())
    for name, table in sections.items():
        items += [(f"[{name}] {k}", v) for k, v in (table or {}).items()]
    blocks.append(key_values("Rig", items))
    dev = dict(s.start.get("device") or {})
    if dev:
        details = dev.pop("details", {}) or {}
        blocks.append(key_values("Device", [*dev.items(), *details.items()]))
    margin = _precheck_table(s)
    if margin:
        blocks.append(margin)
    safety = s.start.get("safety")
    if isinstance(safety, dict) and safety:
        blocks.append(key_values("Safety envelope", list(safety.items())))
    return blocks


def _precheck_table(s: ReportSession) -> Table | None:
    from labbench.model.ve import VirtualEnvironment

    checks = (s.start.get("precheck") or {}).get("checks")
    if not checks:
        return None
    rows, unreadable = [], 0
    for c in checks:
        try:  # the shape is checked at load (report.shapes); the values are the VE's to judge
            ve = VirtualEnvironment.from_dict(c["ve"])
        except (UserError, TypeError) as exc:  # e.g. a key VirtualEnvironment does not take
            logging.getLogger(__name__).info("precheck VE left out: %s", exc)
            unreadable += 1
            continue
        km = c.get("k_max")
        rows.append([ve.kind, fmt(ve.K), fmt(ve.B), fmt(ve.w0) if math.isfinite(ve.w0) else "none",
                     fmt(ve.td * 1e3), fmt(c.get("stable")), fmt(c.get("spectral_radius"), 6),
                     fmt(km), fmt(c.get("k_max_approx")),
                     fmt(km / ve.K) if km and ve.K > 0 else "-"])
    plant = s.plant
    title = "Pre-check against the exact sampled stability boundary"
    if plant:
        title += f" (m = {plant.m:.4g} kg, b = {plant.b:.4g} N s/m)"
    return Table(title, ["VE", "K (N/m)", "B (N s/m)", "w0 (rad/s)", "td (ms)", "stable",
                         "spectral radius", "K_max exact (N/m)", "K_max paper (N/m)", "K_max / K"],
                 rows, note=f"{unreadable} check(s) left out: not a valid VE." if unreadable else "")


def overlay_color(s: ReportSession) -> str:
    """The colour of session ``s`` in overlay figures."""
    return COLORS[(s.index - 1) % len(COLORS)]


def nyquist_band(w: np.ndarray, T: float) -> np.ndarray:
    """Frequencies up to 0.3 x Nyquist: beyond, the sampled loop's own growth near Nyquist
    swamps every panel of a paper-style figure."""
    return np.asarray(w) <= 0.3 * math.pi / T
