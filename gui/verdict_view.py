"""Verdicts in the window: ok / doubtful / failed with the band they speak of, their reasons
and notes, wherever a result shows. The words are ``labbench.readout.wording``'s (the one source of
what the CLI, the report and the window say of a result) and follow the display units."""
from __future__ import annotations

from functools import partial
from html import escape

from PySide6 import QtCore, QtWidgets

from labbench.readout.numfmt import frequencies_in
from labbench.readout.wording import Judged
from labbench.readout.verdict import DOUBTFUL, FAILED, OK, from_dict

COLOURS = {OK: "#206020", DOUBTFUL: "#a86b00", FAILED: "#b00020"}


def judged(what: str, verdict) -> list[Judged]:
    """A recorded verdict (a dict, not trusted) as a readout's ``Judged``; [] when it is none."""
    v = from_dict(verdict)
    return [] if v is None else [Judged(what, v)]


OUTSIDE = "outside the band"  # how a note of what lies beyond the verdict's band starts
# what a note means for the numbers (labbench.readout.verdict: a limit that does not raise the level)
NOTES_MEAN = ("the notes do not change the level: inside the band they widen the 95 % intervals "
              "there and of what is read from there (K, B), which still hold the truth; outside "
              "it they do not touch what is read in it")


def verdict_html(j: Judged, units=None, explain: bool = True) -> str:
    """``what: ok over 2-100 rad/s`` in the level's colour, then its reasons and its notes,
    those inside its band first, and what notes mean for the numbers; frequencies in the
    display units."""
    v = j.verdict
    head = f'<b style="color:{COLOURS[v.level]}">{escape(j.what)}: {escape(v.head(units))}</b>'
    notes = sorted(v.notes, key=lambda n: n.startswith(OUTSIDE))  # stable: inside first
    lines = [*v.reasons, *(f"note: {n}" for n in notes)]
    body = "".join(f"<br>&nbsp;&nbsp;- {escape(frequencies_in(x, units))}" for x in lines)
    if v.notes and explain:
        body += f'<br>&nbsp;&nbsp;<i style="color:#555555">({escape(NOTES_MEAN)})</i>'
    return head + body


def result_lines(read) -> list:
    """The first lines of a result on the Live page: its rendered impedance, or, for a result
    with neither that nor a verdict (a stability probe's boundary), its headline rows as
    the report's page 1 keeps them (a probe's K_max was in the log alone)."""
    if read is None or read.rendered is not None or read.verdicts:
        return rendered_line(read)
    keep = read.headline
    return [partial(_row_line, read, label) for label, _v in read.rows
            if keep is None or label in keep]


def _row_line(read, label: str, units=None) -> str:
    return f"{label}: {dict(read.row_texts(units))[label]}"


def rendered_line(read) -> list:
    """The readout's rendered impedance as the first line of the verdicts (in the display
    units; in its verdict's colour when the ETFE does not vouch for it), or none."""
    r = read.rendered if read is not None else None
    if r is None:
        return []
    level = OK if r.trust is None else r.trust.level
    return [r.sentence if level == OK else (r.sentence, COLOURS[level])]


class VerdictLabel(QtWidgets.QLabel):
    """The verdicts of one result, one per line, under a heading and lines of its own (the
    rendered impedance, what was not replaced); with none, hidden, or the ``placeholder``
    (in grey) where the label keeps its room. ``set_units`` writes them again."""

    def __init__(self, parent=None, placeholder: str = ""):
        super().__init__(parent)
        self.setWordWrap(True)
        self.setTextFormat(QtCore.Qt.TextFormat.RichText)
        self.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
        self.setAlignment(QtCore.Qt.AlignmentFlag.AlignLeft | QtCore.Qt.AlignmentFlag.AlignTop)
        self.placeholder = placeholder
        self.units = None
        self.shown: list[Judged] = []
        self._heading, self._lines = "", []
        self.show_judged([])

    def show_judged(self, verdicts: list[Judged], heading: str = "",
                    lines=()) -> None:
        """``verdicts`` under ``heading`` (HTML) and ``lines``: plain text, a callable of the
        display units giving it (a readout's ``rendered.sentence``), or (either, colour)."""
        self.shown, self._heading, self._lines = list(verdicts), heading, list(lines)
        self._write()

    def set_units(self, units) -> None:
        self.units = units
        self._write()

    def _write(self) -> None:
        def text(x) -> str:
            return escape(x(self.units) if callable(x) else x)

        extra = [f'<span style="color:{x[1]}">{text(x[0])}</span>' if isinstance(x, tuple)
                 else text(x) for x in self._lines]
        noted = next((j for j in self.shown if j.verdict.notes), None)  # what notes mean: once
        body = extra + [verdict_html(j, self.units, j is noted) for j in self.shown]
        text = "<br>".join(([self._heading] if self._heading and body else []) + body)
        if not text and self.placeholder:
            text = f'<span style="color:#777777">{escape(self.placeholder)}</span>'
        self.setText(text)
        self.setVisible(bool(text))

    def levels(self) -> dict[str, str]:
        """what -> level of the verdicts shown (for tests and screenshots' checks)."""
        return {j.what: j.verdict.level for j in self.shown}
