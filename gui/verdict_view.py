"""Verdicts in the window: ok / doubtful / failed with the reasons, wherever a result shows
(``labbench.verdict``: each analysis judges its own result; the window says what it said)."""
from __future__ import annotations

from html import escape

from PySide6 import QtCore, QtWidgets

from labbench.verdict import DOUBTFUL, FAILED, OK, from_dict

COLOURS = {OK: "#206020", DOUBTFUL: "#a86b00", FAILED: "#b00020"}


def verdicts_of(results: dict) -> list[tuple[str, dict]]:
    """(what, verdict dict) of every verdict a run's results carry, in a person's words:
    the result's own, each identification fit's, the ETFE's and the loop fit's, each
    commissioning check's (recorded results are not trusted: what is not a verdict is left out)."""
    if not isinstance(results, dict):
        return []
    names = {"etfe": "ETFE", "loop_fit": "closed-loop fit", "k_max": "K_max"}
    found = []
    if from_dict(results.get("verdict")):
        found.append(("commissioning" if "changes" in results else "result", results["verdict"]))
    ident = results.get("identification")
    for method, fit in (ident.items() if isinstance(ident, dict) else ()):
        if isinstance(fit, dict) and from_dict(fit.get("verdict")):
            found.append((f"identification ({method})", fit["verdict"]))
    for key, value in results.items():
        if key not in ("identification", "verdict") and isinstance(value, dict) \
                and from_dict(value.get("verdict")):
            found.append((names.get(key, key.replace("_", " ")), value["verdict"]))
    return found


def verdict_html(what: str, verdict: dict) -> str:
    """``what: level`` in the level's colour, then its reasons (escaped)."""
    v = from_dict(verdict)
    if v is None:
        return ""
    head = f'<b style="color:{COLOURS[v.level]}">{escape(what)}: {v.level}</b>'
    return head + "".join(f"<br>&nbsp;&nbsp;- {escape(r)}" for r in v.reasons)


class VerdictLabel(QtWidgets.QLabel):
    """The verdicts of one result, one per line; hidden when there are none."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.setWordWrap(True)
        self.setTextFormat(QtCore.Qt.TextFormat.RichText)
        self.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
        self.shown: list[tuple[str, dict]] = []
        self.setVisible(False)

    def show_verdicts(self, verdicts: list[tuple[str, dict]], prefix: str = "",
                      always: bool = False) -> None:
        """One line per verdict under ``prefix``; ``always``: the prefix is shown even with
        no verdict (it says something by itself)."""
        self.shown = [(w, v) for w, v in verdicts if from_dict(v) is not None]
        lines = [verdict_html(w, v) for w, v in self.shown]
        self.setText((prefix + "<br>" if prefix and lines else prefix if always else "")
                     + "<br>".join(lines))
        self.setVisible(bool(lines) or always)

    def levels(self) -> dict[str, str]:
        """what -> level of the verdicts shown (for tests and screenshots' checks)."""
        return {w: v["level"] for w, v in self.shown}
