"""Run reports: one self-contained HTML (figures inline as base64 PNG) and one PDF.

A report covers one or more sessions. Per session: the run (identity, status,
samples, drops), the rig, the protocol settings, the stability margin of the VE
(exact sampled model, ``labbench.theory``), the protocol's results as recorded
in the stop record (identification table, ETFE accuracy and bandwidths, the
stability-probe steps), paper-style figures of data against theory
(``labbench.figures.paper_figure``), an overview of the recorded channels, the
safety events and the loop timing.

The content is built once as a list of blocks (heading, table, text, figure)
and rendered twice: to HTML and, through matplotlib's PdfPages, to PDF.
"""
from __future__ import annotations

import base64
import html
import io
import math
import tempfile
import textwrap
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure

from labbench.errors import UserError
from labbench.escape import literal_mpl, one_line
from labbench.numfmt import fmt
from labbench.records import protocol_name
from labbench.safe_write import output_folder, output_path, replacing
from labbench.session_content import load_session, session_ve
from labbench.ve import Plant

A4 = (8.27, 11.69)  # inches


# ---------------------------------------------------------------- content blocks

@dataclass
class Heading:
    text: str
    level: int = 2


@dataclass
class Text:
    text: str


@dataclass
class Table:
    title: str
    header: list[str]
    rows: list[list[str]]


@dataclass
class Picture:
    caption: str
    png: bytes
    figure: Figure | None = field(default=None, repr=False)  # vector source for the PDF


def _kv(title: str, items) -> Table:
    return Table(title, ["", ""], [[str(k), fmt(v)] for k, v in items])


def _png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    return buf.getvalue()


def _new_figure(size=(10, 6)) -> Figure:
    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


# ---------------------------------------------------------------- one session

@dataclass
class SessionData:
    path: Path
    start: dict
    desc: dict
    ch: dict
    events: list
    stop: dict | None
    problem: str | None

    @property
    def results(self) -> dict:
        return dict((self.stop or {}).get("results") or {})

    @property
    def T(self) -> float:
        rig = self.start.get("rig") or {}
        return float(self.desc.get("sample_time_s") or rig.get("sample_time_s") or 0.001)

    @property
    def plant(self) -> Plant | None:
        for p in (self.results.get("plant"), self.start.get("plant")):
            if isinstance(p, dict) and "m" in p and "b" in p:
                return Plant(float(p["m"]), float(p["b"]))
        return None


def _load(path) -> SessionData:
    return SessionData(Path(path), *load_session(path))


def _run_table(s: SessionData) -> Table:
    stop = s.stop or {}
    t = s.ch["t"]
    seq = s.ch["seq"].astype(np.int64)
    dropped = int(np.sum(np.clip(np.diff(seq) - 1, 0, None))) if seq.size > 1 else 0
    started = s.start.get("time")
    return _kv("Run", [
        ("session file", s.path.name),
        ("uid", s.start.get("uid")),
        ("started", time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(started)) if started else None),
        ("software", s.start.get("software")),
        ("device", (s.start.get("device") or {}).get("kind")),
        ("status", stop.get("status", "incomplete (no stop record)")),
        ("reason", stop.get("reason")),
        ("samples", int(t.size)),
        ("duration (s)", float(t[-1] - t[0]) if t.size else 0.0),
        ("dropped samples", dropped),
        ("seed", s.start.get("seed")),
        ("file damage", s.problem or "none"),
    ])


def _rig_table(s: SessionData) -> Table:
    rig = dict(s.start.get("rig") or {})
    sections = rig.pop("sections", {}) or {}
    items = list(rig.items())
    for name, table in sections.items():
        items += [(f"[{name}] {k}", v) for k, v in (table or {}).items()]
    return _kv("Rig", items)


def _device_table(s: SessionData) -> Table | None:
    dev = dict(s.start.get("device") or {})
    if not dev:
        return None
    details = dev.pop("details", {}) or {}
    return _kv("Device", [*dev.items(), *((f"  {k}", v) for k, v in details.items())])


def _protocol_table(s: SessionData) -> Table:
    proto = s.start.get("protocol")
    items = proto.items() if isinstance(proto, dict) else [("protocol", proto)]
    return _kv(f"Protocol: {protocol_name(s.start)}", items)


def _stability_table(s: SessionData) -> Table | None:
    """Margin of the VE(s): the precheck of the run, or the theory engine on the start VE."""
    from labbench import theory
    from labbench.ve import VirtualEnvironment

    checks = (s.start.get("precheck") or {}).get("checks")
    plant = s.plant
    if not checks:
        ve = session_ve(s.start)
        if ve is None or plant is None:
            return None
        st = theory.stability(plant, ve)
        checks = [{"ve": ve.as_dict(), "stable": st.stable, "spectral_radius": st.spectral_radius,
                   "k_max": theory.k_max(plant, ve), "k_max_approx": theory.k_max_approx(plant, ve)}]
    rows = []
    for c in checks:
        ve = VirtualEnvironment.from_dict(c["ve"])
        km = c.get("k_max")
        margin = km / ve.K if km and ve.K > 0 else None
        rows.append([ve.kind, fmt(ve.K), fmt(ve.B), fmt(ve.td * 1e3), fmt(c.get("stable")),
                     fmt(c.get("spectral_radius")), fmt(km), fmt(c.get("k_max_approx")),
                     fmt(margin)])
    title = "Stability margin (exact sampled model"
    title += f", m = {plant.m:.4g} kg, b = {plant.b:.4g} N s/m)" if plant else ")"
    return Table(title, ["VE", "K (N/m)", "B (N s/m)", "td (ms)", "stable", "spectral radius",
                         "K_max exact (N/m)", "K_max paper (N/m)", "K_max / K"], rows)


def _identification_table(ident: dict) -> Table:
    rows = []
    for method, r in ident.items():
        ci = r.get("ci95") or {}
        rows.append([method, str(r.get("model")), fmt(r.get("m"), 6), fmt(ci.get("m"), 6),
                     fmt(r.get("b"), 6), fmt(ci.get("b"), 6), fmt(r.get("coulomb")),
                     fmt(r.get("offset")), fmt(r.get("rms_residual")), fmt(r.get("explained"), 6),
                     str(r.get("n_used"))])
    return Table("Identification f = m x'' + b x' [+ Fc sign(x')] [+ f0]",
                 ["method", "model", "m (kg)", "m 95 %", "b (N s/m)", "b 95 %", "Fc (N)",
                  "f0 (N)", "rms residual (N)", "explained", "samples"], rows)


def _identification_notes(ident: dict) -> list:
    out = []
    for method, r in ident.items():
        sel = r.get("selection") or {}
        if sel:
            out.append(Text(f"{method}: model {sel.get('model')} chosen by {sel.get('criterion')}"))
        for flag in r.get("flags") or []:
            out.append(Text(f"{method} flag: {flag}"))
    return out


def _paper_figure_png(curves, title: str, marks: dict) -> bytes:
    from labbench.figures import paper_figure

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "figure.png"
        paper_figure(curves, path, title=title, marks=marks)
        return path.read_bytes()


def _etfe_blocks(s: SessionData) -> list:
    """ETFE sessions: accuracy and bandwidths from the stop record; figure from the protocol's
    own analysis (its arrays are not kept in the stop record)."""
    from labbench.figures import Curve
    from labbench.registry import make_protocol

    res = s.results
    blocks = []
    dev = res.get("deviation_vs_sampled") or {}
    if dev:
        band = dev.get("band_rad_s") or [None, None]
        blocks.append(_kv("ETFE against the exact sampled theory", [
            ("band (rad/s)", band), ("median |Z - Z_theory| / |Z_theory|", dev.get("median_rel")),
            ("max |Z - Z_theory| / |Z_theory|", dev.get("max_rel")),
            ("frequencies", dev.get("n_points"))]))
    bw = res.get("bandwidths") or {}
    if bw:
        blocks.append(Table("Bandwidths (rad/s)", ["", "measured", "predicted"], [
            ["w_s* (stiffness)", fmt(bw.get("ws_star_measured")), fmt(bw.get("ws_star_predicted"))],
            ["w_b* (damping)", fmt(bw.get("wb_star_measured")), fmt(bw.get("wb_star_predicted"))]]))
    proto = dict(s.start.get("protocol") or {})
    name = proto.pop("protocol", None) or proto.pop("name", "etfe")
    full = make_protocol(name, **proto).analyze(
        s.ch, {"plant": {"m": s.plant.m, "b": s.plant.b}} if s.plant else {})
    e, th = full["etfe"], full["theory"]
    w = np.asarray(e["w"])
    # up to 30 % of Nyquist: beyond, the sampled model's growth near Nyquist swamps the panels
    keep = w <= 0.3 * math.pi / s.T
    Z = np.asarray(e["Z_re"]) + 1j * np.asarray(e["Z_im"])
    err = None if e.get("Z_err") is None else np.asarray(e["Z_err"])[keep]

    def theory_Z(model):
        return (np.asarray(th[model]["Z_re"]) + 1j * np.asarray(th[model]["Z_im"]))[keep]

    curves = [Curve("exact sampled theory", w[keep], theory_Z("sampled")),
              Curve("paper eq. 2", w[keep], theory_Z("paper")),
              Curve("measured (ETFE)", w[keep], Z[keep], "points", err)]
    marks = {"ws*": bw.get("ws_star_measured"), "wb*": bw.get("wb_star_measured")}
    ve = session_ve(s.start)
    title = f"{ve.kind} K = {ve.K:g} N/m, B = {ve.B:g} N s/m, w0 = {ve.w0:g} rad/s" if ve else None
    blocks.append(Picture("Closed-loop impedance and effective impedances: data vs theory",
                          _paper_figure_png(curves, title, marks)))
    return blocks


def _chirp_blocks(s: SessionData) -> list:
    """Chirp-ID sessions: the identification table; the open-loop ETFE against Z = b + j w m
    of the identified plant (exact sampled model, VE off)."""
    from labbench.analysis.compare import theory_curves
    from labbench.analysis.dataio import recording_from_arrays
    from labbench.analysis.etfe import etfe
    from labbench.figures import Curve
    from labbench.ve import VirtualEnvironment

    ident = s.results.get("identification") or {}
    blocks = [_identification_table(ident), *_identification_notes(ident)] if ident else []
    proto = s.start.get("protocol") or {}
    rec = recording_from_arrays(s.ch["t"], s.ch["command"], s.ch["position"], {"fs": 1 / s.T})
    est = etfe(rec)
    w, Z = np.asarray(est.w), np.asarray(est.Z)
    # the excited band only: outside it the ratio is noise
    keep = (w >= 2 * math.pi * float(proto.get("f0_hz", 0))) & (
        w <= 2 * math.pi * float(proto.get("f1_hz", math.inf)))
    ve = VirtualEnvironment("none", T=s.T)
    curves = []
    for method, r in ident.items():
        if r.get("m") and r.get("b") is not None:
            plant = Plant(float(r["m"]), float(r["b"]))
            curves.append(Curve(f"identified {method}: m = {plant.m:.4g}, b = {plant.b:.4g}",
                                w[keep], theory_curves(plant, ve, w[keep])["Z"]))
    curves.append(Curve("measured (ETFE)", w[keep], Z[keep], "points"))  # drawn on top
    blocks.append(Picture("Open-loop impedance during the chirp: data vs identified model",
                          _paper_figure_png(curves, "chirp identification, VE off", {})))
    return blocks


def _stability_blocks(s: SessionData) -> list:
    res = s.results
    steps = res.get("steps") or []
    var = res.get("variable", "K")
    blocks = [_kv("Stability boundary", [
        ("variable", var), ("measured", res.get("measured_boundary")),
        ("exact sampled prediction", res.get("exact_boundary")),
        ("paper approximation", res.get("approx_boundary")),
        ("measured vs exact (rel.)", res.get("rel_error_vs_exact")),
        ("approximation vs measured (rel.)", res.get("rel_error_approx_vs_measured"))])]
    if steps:
        blocks.append(Table("Probe steps", ["K (N/m)", "td (ms)", "status", "growth rate (1/s)",
                                            "unstable"],
                            [[fmt(p.get("K")), fmt(1e3 * p.get("td_s", 0.0)), str(p.get("status")),
                              fmt(p.get("sigma_per_s")), fmt(p.get("unstable"))] for p in steps]))
        key = "K" if var == "K" else "td_s"
        x = np.array([p.get(key) for p in steps], float)
        sig = np.array([np.nan if p.get("sigma_per_s") is None else p["sigma_per_s"]
                        for p in steps])
        fig = _new_figure((9, 4.5))
        ax = fig.add_subplot()
        ax.plot(x, sig, "o-", label="measured growth rate")
        for name, v, style in (("measured", res.get("measured_boundary"), "-"),
                               ("exact sampled", res.get("exact_boundary"), "--"),
                               ("paper approx.", res.get("approx_boundary"), ":")):
            if v is not None:
                ax.axvline(v, color="0.3", ls=style, label=f"{name} boundary {v:.4g}")
        ax.axhline(0, color="k", lw=0.5)
        ax.set_xlabel("K (N/m)" if var == "K" else "td (s)")
        ax.set_ylabel("growth rate sigma (1/s)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        blocks.append(Picture("Stability probe: growth rate per step against the boundaries",
                              _png(fig), fig))
    return blocks


def _overview_figure(s: SessionData) -> Picture | None:
    t = s.ch["t"]
    if t.size == 0:
        return None
    step = max(1, t.size // 20000)  # plenty of points for a page-wide plot
    sl = slice(None, None, step)
    fig = _new_figure((10, 6.5))
    axes = fig.subplots(3, 1, sharex=True)
    axes[0].plot(t[sl], 1e3 * s.ch["position"][sl], lw=0.6)
    axes[0].set_ylabel("position (mm)")
    axes[1].plot(t[sl], s.ch["velocity"][sl], lw=0.6)
    axes[1].set_ylabel("velocity est. (m/s)")
    for name in ("excitation", "ve_force", "command"):
        axes[2].plot(t[sl], s.ch[name][sl], lw=0.6, label=name)
    axes[2].set_ylabel("force (N)")
    axes[2].set_xlabel("time (s)")
    axes[2].legend(fontsize=8, loc="upper right")
    trips = [e for e in s.events if e.get("name") not in ("segment", "enabled")
             and e.get("t") is not None]
    for ax in axes:
        ax.grid(alpha=0.3)
        for e in trips:
            ax.axvline(e["t"], color="r", lw=0.8, alpha=0.6)
    return Picture("Recorded channels (red lines: safety events)", _png(fig), fig)


def _events_table(s: SessionData) -> Table:
    rows = [[fmt(e.get("t")), str(e.get("name")), str(e.get("reason"))] for e in s.events]
    return Table(f"Events ({len(rows)})", ["t (s)", "event", "reason"],
                 rows or [["-", "none", ""]])


def _timing_table(s: SessionData) -> Table:
    from labbench.timing import report_rows

    return _kv("Loop timing", report_rows((s.stop or {}).get("timing") or {}))


def session_blocks(path) -> list:
    """The report content of one session."""
    s = _load(path)
    blocks: list = [Heading(f"{protocol_name(s.start)} - {s.path.name}"), _run_table(s)]
    if s.problem:
        blocks.append(Text(f"Warning: the file ends early ({s.problem}); "
                           "everything before that point is shown."))
    blocks += [b for b in (_rig_table(s), _device_table(s), _protocol_table(s)) if b]
    margin = _stability_table(s)
    if margin:
        blocks.append(margin)
    if s.results.get("error"):
        blocks.append(Text(f"Analysis failed during the run: {s.results['error']}"))
    name = protocol_name(s.start)
    if s.ch["t"].size and s.results:
        builder = {"etfe": _etfe_blocks, "chirp-id": _chirp_blocks,
                   "stability": _stability_blocks}.get(name)
        if builder:
            try:
                blocks += builder(s)
            except UserError as exc:
                blocks.append(Text(f"Analysis for the figures failed: {exc}"))
    elif not s.results:
        blocks.append(Text("No results recorded (the run did not finish its analysis)."))
    overview = _overview_figure(s)
    if overview:
        blocks.append(overview)
    blocks += [_events_table(s), _timing_table(s)]
    return blocks


# ---------------------------------------------------------------- renderers

_CSS = """body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.2em}td,th{border:1px solid #ccc;padding:2px 8px;
font-size:13px;text-align:left}caption{font-weight:bold;text-align:left;padding:4px 0}
img{max-width:100%}figure{margin:1em 0}figcaption{font-style:italic;font-size:13px}"""


def render_html(title: str, blocks: list) -> str:
    e = html.escape
    out = [(f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{e(title)}</title>"
            f"<style>{_CSS}</style></head><body><h1>{e(title)}</h1>")]
    for b in blocks:
        if isinstance(b, Heading):
            out.append(f"<h{b.level}>{e(b.text)}</h{b.level}>")
        elif isinstance(b, Text):
            out.append(f"<p>{e(b.text)}</p>")
        elif isinstance(b, Table):
            head = "" if not any(b.header) else (
                "<tr>" + "".join(f"<th>{e(h)}</th>" for h in b.header) + "</tr>")
            body = "".join("<tr>" + "".join(f"<td>{e(c)}</td>" for c in row) + "</tr>"
                           for row in b.rows)
            out.append(f"<table><caption>{e(b.title)}</caption>{head}{body}</table>")
        elif isinstance(b, Picture):
            data = base64.b64encode(b.png).decode()
            out.append(f"<figure><img alt='{e(b.caption)}' src='data:image/png;base64,{data}'>"
                       f"<figcaption>{e(b.caption)}</figcaption></figure>")
    out.append("</body></html>")
    return "\n".join(out)


def _table_lines(t: Table, width: int = 110) -> list[str]:
    """A table as aligned monospace lines, long cells wrapped."""
    cols = len(t.header)
    rows = ([t.header] if any(t.header) else []) + t.rows
    widths = [max([len(r[i]) for r in rows] + [1]) for i in range(cols)]
    budget = width - 2 * (cols - 1)
    while sum(widths) > budget and max(widths) > 8:
        widths[widths.index(max(widths))] -= 1
    lines = [t.title]
    for r in rows:
        wrapped = [textwrap.wrap(c, widths[i]) or [""] for i, c in enumerate(r)]
        for k in range(max(len(w) for w in wrapped)):
            lines.append("  ".join((w[k] if k < len(w) else "").ljust(widths[i])
                                   for i, w in enumerate(wrapped)).rstrip())
        if r is t.header:
            lines.append("-" * min(width, sum(widths) + 2 * (cols - 1)))
    return lines + [""]


def render_pdf(title: str, blocks: list, path: Path) -> None:
    """A4 pages: text and tables in monospace, one figure per page (vector when possible)."""
    line_h, top, bottom = 0.0118, 0.95, 0.04
    per_page = int((top - bottom) / line_h)
    # per session (a Heading starts one): its text and tables flow first, its figures follow
    ordered, figures = [], []
    for b in blocks:
        if isinstance(b, Heading):
            ordered += figures
            figures = []
        (figures if isinstance(b, Picture) else ordered).append(b)
    blocks = ordered + figures
    with PdfPages(path) as pdf:
        pdf.infodict()["Title"] = title
        big = {"size": 11, "weight": "bold", "family": "sans-serif"}  # two line slots each
        lines: list[tuple[str, dict]] = []
        for t in textwrap.wrap(title, 90):
            lines += [(t, big), ("", {})]
        first_heading = True

        def flush_text():
            while lines:
                page, rest = lines[:per_page], lines[per_page:]
                fig = Figure(figsize=A4)
                for i, (text, style) in enumerate(page):
                    fig.text(0.06, top - i * line_h, literal_mpl(one_line(text)),
                             family=style.get("family", "monospace"), size=style.get("size", 7),
                             weight=style.get("weight", "normal"), va="top")
                pdf.savefig(fig)
                lines[:] = rest

        for b in blocks:
            if isinstance(b, Heading):
                if not first_heading:
                    flush_text()  # each session starts on a new page
                first_heading = False
                lines += [("", {}), (b.text, big), ("", {})]
            elif isinstance(b, Text):
                lines += [(w, {}) for w in textwrap.wrap(b.text, 110)] + [("", {})]
            elif isinstance(b, Table):
                tl = _table_lines(b)
                if len(lines) % per_page + len(tl) > per_page and len(tl) < per_page:
                    lines += [("", {})] * (per_page - len(lines) % per_page)  # keep it on one page
                lines += [(tl[0], {"weight": "bold"})] + [(x, {}) for x in tl[1:]]
            elif isinstance(b, Picture):
                flush_text()
                if b.figure is not None:
                    b.figure.suptitle(literal_mpl(b.caption), fontsize=10)
                    pdf.savefig(b.figure)
                else:
                    fig = Figure(figsize=(A4[1], A4[0]))  # landscape page for wide figures
                    ax = fig.add_axes((0.02, 0.02, 0.96, 0.9))
                    ax.imshow(_decode_png(b.png))
                    ax.set_axis_off()
                    fig.suptitle(literal_mpl(b.caption), fontsize=10)
                    pdf.savefig(fig)
        flush_text()


def _decode_png(png: bytes) -> np.ndarray:
    from matplotlib import image

    return image.imread(io.BytesIO(png), format="png")


def write_report(session_path, out_dir, force: bool = False) -> tuple[Path, Path]:
    """Write ``<name>.html`` and ``<name>.pdf`` into ``out_dir`` for one session or a list.

    Returns ``(html_path, pdf_path)``. Raises UserError for a missing or foreign
    session file or an unusable output folder (created if missing, never its
    parents); existing outputs are replaced only with ``force``, each atomically
    (``labbench.safe_write``).
    """
    paths = [session_path] if isinstance(session_path, (str, Path)) else list(session_path)
    if not paths:
        raise UserError("no session given")
    out = Path(out_dir)
    stem = Path(paths[0]).stem + (f"+{len(paths) - 1}" if len(paths) > 1 else "")
    html_path, pdf_path = out / f"{stem}.html", out / f"{stem}.pdf"
    if out.exists() and not out.is_dir():
        raise UserError(f"output {out} is a file, not a directory")
    if out.is_dir():  # before the work: refuse what would be refused at the end
        for target in (html_path, pdf_path):
            output_path(target, paths, force)
    elif not out.parent.is_dir():
        raise UserError(f"cannot create output folder {out}: {out.parent} does not exist "
                        "(labbench creates no folders you did not name)")
    blocks = []
    for p in paths:
        blocks += session_blocks(p)
    output_folder(out)
    title = "labbench report: " + ", ".join(Path(p).name for p in paths)
    try:
        with replacing(html_path, paths, force) as tmp:
            tmp.write_text(render_html(title, blocks), encoding="utf-8")
        with replacing(pdf_path, paths, force) as tmp:
            render_pdf(title, blocks, tmp)
    except OSError as exc:
        raise UserError(f"cannot write report into {out}: {exc.strerror or exc}") from None
    return html_path, pdf_path
