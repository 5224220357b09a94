"""The content of a report as plain data, rendered by ``report.html`` and ``report.pdf``.

Text is plain (renderers escape it) unless it is ``Markup``: a trusted string
with only ``<i>``, ``<b>``, ``<sub>`` and ``<sup>`` tags, for symbols such as
ω<sub>b</sub>* in the report's own labels. Strings from sessions (rig names,
reasons, flags) are always plain.
"""
from __future__ import annotations

import html
import io
from dataclasses import dataclass, field

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure as MplFigure

from labbench.readout.escape import one_line
from labbench.readout.numfmt import fmt, fmt_ci  # noqa: F401 - the one number formatter, for sections too


class Markup(str):
    """Report-authored text with <i>, <b>, <sub>, <sup> tags (never session text)."""


def as_markup(text) -> str:
    """``text`` as markup: Markup as it is, anything else escaped (and on one line, control
    characters shown as escapes: ``labbench.readout.escape.one_line``)."""
    return str(text) if isinstance(text, Markup) else html.escape(one_line(text), quote=False)


@dataclass
class Heading:
    text: str
    level: int = 2  # 1: part (Summary, Details, Appendix), 2: session, 3: section


@dataclass
class Paragraph:
    text: str
    style: str = "body"  # "body", "note" (small), "warning"


@dataclass
class Table:
    """A table: ``columns`` are header cells (units in parentheses; empty list: no header,
    e.g. a label/value list); ``rows`` are cells as text (numbers already formatted).
    Columns whose cells all look numeric are right-aligned."""

    title: str
    columns: list
    rows: list
    note: str = ""

    def numeric(self) -> list[bool]:
        n = max([len(self.columns)] + [len(r) for r in self.rows])
        return [bool(self.rows) and all(_looks_numeric(r[i]) for r in self.rows if i < len(r))
                for i in range(n)]


@dataclass
class Figure:
    caption: str
    figure: MplFigure = field(repr=False)
    width: float = 1.0  # fraction of the text width

    def png(self, dpi: int = 150) -> bytes:
        buf = io.BytesIO()
        self.figure.savefig(buf, format="png", dpi=dpi)
        return buf.getvalue()


@dataclass
class Flag:
    """Something the reader must know about a run, and what to do about it."""

    session: str  # "#2" etc.
    problem: str
    action: str


@dataclass
class PageBreak:
    pass


@dataclass
class ReportSections:
    """A protocol's part of a report (``labbench.protocol.ProtocolBase.report_sections``).

    Page 1's numbers and verdicts are not the protocol's to write: the report reads them
    from ``labbench.readout.wording`` as the CLI and the window do. ``curves``:
    frequency responses for the summary's overlay figure (``labbench.readout.figures.Curve``,
    measured as points, theory as lines). ``flags``: problems with what to do.
    ``details``: blocks for the session's part of the details. ``margin``: whether the
    summary adds the run's stability margin and loop delay to its numbers (a protocol
    whose result is the stability boundary itself says no). ``delay``: the loop delay
    as measured by the protocol's analysis (text), None when it measured none.
    """

    curves: list = field(default_factory=list)
    flags: list = field(default_factory=list)
    details: list = field(default_factory=list)
    margin: bool = True
    delay: str | None = None


def percent(v, digits: int = 2) -> str:
    return "-" if v is None else f"{fmt(100 * v, digits)} %"


def key_values(title: str, items, note: str = "") -> Table:
    """A label/value table without a header."""
    return Table(title, [], [[str(k), v if isinstance(v, str) else fmt(v)] for k, v in items], note)


def new_figure(size=(7.2, 3.6)) -> MplFigure:
    """A matplotlib figure on the Agg canvas (no pyplot state), sized in inches for A4 text."""
    fig = MplFigure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _looks_numeric(cell) -> bool:
    text = str(cell).strip().replace(" %", "").replace("−", "-")
    if text in ("-", ""):
        return True
    try:
        float(text.split(" / ")[0].split(" to ")[0])
    except ValueError:
        return False
    return True
