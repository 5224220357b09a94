"""The event log: every message, safety trip and error of the session, newest last."""
from __future__ import annotations

import time

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

    def add(self, level: str, text: str) -> None:
        now = time.time()
        self.entries.append((now, level, text))
        stamp = time.strftime("%H:%M:%S", time.localtime(now))
        colour = LEVEL_COLOURS.get(level, LEVEL_COLOURS["info"])
        safe = text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
        self.appendHtml(f'<span style="color:{colour}">{stamp} [{level}] {safe}</span>')

    def texts(self, level: str | None = None) -> list[str]:
        return [t for _, lv, t in self.entries if level is None or lv == level]
