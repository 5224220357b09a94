"""The event log: every message, safety trip and error of the session, newest last.

It follows its newest line unless the user has scrolled up to read an older one (then
it stays there until they scroll back to the bottom)."""
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

    def add(self, level: str, text: str, rows: list[tuple[str, str]] | None = None) -> None:
        """One line; ``rows`` (label, value) follow it as an aligned two-column table."""
        now = time.time()
        self.entries.append((now, level, text))
        stamp = time.strftime("%H:%M:%S", time.localtime(now))
        colour = LEVEL_COLOURS.get(level, LEVEL_COLOURS["info"])
        lines = [f"{stamp} [{level}] {text}"]
        if rows:
            width = max(len(label) for label, _ in rows)
            lines += [f"    {label.ljust(width)}  {value}" for label, value in rows]
        following = self.following()
        safe = "<br>".join(escape(line, quote=False).replace("  ", "&nbsp;&nbsp;") for line in lines)
        self.appendHtml(f'<span style="color:{colour}">{safe}</span>')
        if following:
            bar = self.verticalScrollBar()
            bar.setValue(bar.maximum())

    def following(self) -> bool:
        """Whether the view is at the bottom: the newest line in view (or nothing to scroll)."""
        bar = self.verticalScrollBar()
        return bar.value() >= bar.maximum() - 2

    def texts(self, level: str | None = None) -> list[str]:
        return [t for _, lv, t in self.entries if level is None or lv == level]

