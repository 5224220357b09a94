"""The event log: every message, safety trip and error of the session, newest last.

It follows its newest line unless the person has scrolled up to read an older one (then
it stays there until they scroll back to the bottom). Whether it follows is decided by
the person's own scrolling, not by where the scroll bar happens to be after a long entry
(a table of results grows the document after its layout, and reading the bar then left
the log behind for good). An E-STOP line is always brought into view.
"""
from __future__ import annotations

import time
from html import escape

from PySide6 import QtGui, QtWidgets

LEVEL_COLOURS = {"info": "#202020", "event": "#1f5fa8", "warning": "#a86b00", "error": "#b00020"}


class EventLog(QtWidgets.QPlainTextEdit):
    """Read-only, append-only log; ``entries`` keeps (time, level, text) for tests and export."""

    def __init__(self, parent=None, max_lines: int = 2000):
        super().__init__(parent)
        self.setReadOnly(True)
        self.setMaximumBlockCount(max_lines)
        self.setFont(QtGui.QFontDatabase.systemFont(QtGui.QFontDatabase.SystemFont.FixedFont))
        self.entries: list[tuple[float, str, str]] = []
        self._follow = True
        self._moving = False  # the log itself moves the bar (not the person)
        bar = self.verticalScrollBar()
        bar.valueChanged.connect(self._scrolled)
        bar.rangeChanged.connect(lambda *_: self._follow and self._to_end())

    def add(self, level: str, text: str, rows: list[tuple[str, str]] | None = None,
            show: bool = False) -> None:
        """One line; ``rows`` (label, value) follow it as an aligned two-column table.
        ``show``: bring it into view even if the person had scrolled up (an E-STOP)."""
        now = time.time()
        self.entries.append((now, level, text))
        stamp = time.strftime("%H:%M:%S", time.localtime(now))
        colour = LEVEL_COLOURS.get(level, LEVEL_COLOURS["info"])
        lines = [f"{stamp} [{level}] {text}"]
        if rows:
            width = max(len(label) for label, _ in rows)
            lines += [f"    {label.ljust(width)}  {value}" for label, value in rows]
        safe = "<br>".join(escape(line, quote=False).replace("  ", "&nbsp;&nbsp;") for line in lines)
        self.appendHtml(f'<span style="color:{colour}">{safe}</span>')
        self._follow = self._follow or show
        if self._follow:
            self._to_end()

    def following(self) -> bool:
        """Whether the log follows its newest line (the person has not scrolled up)."""
        return self._follow

    def _to_end(self) -> None:
        self._moving = True
        bar = self.verticalScrollBar()
        bar.setValue(bar.maximum())
        self._moving = False

    def _scrolled(self, value: int) -> None:
        if not self._moving:  # the person scrolled: follow again once at the bottom
            self._follow = value >= self.verticalScrollBar().maximum() - 2

    def texts(self, level: str | None = None) -> list[str]:
        return [t for _, lv, t in self.entries if level is None or lv == level]
