"""What the window remembers between sessions (QSettings): its geometry and dock state,
the splitter positions, the open tab, the device backend, the rig file and sessions
folder last used, the protocol chosen and the settings of each protocol.

``open_settings(path)`` gives an INI file at ``path`` (tests, portable set-ups) or the
platform's own store (``~/.config/labbench/labbench.conf`` on Linux). A window made
without settings remembers nothing (the test suite's windows stay independent).
"""
from __future__ import annotations

import json
from pathlib import Path

from PySide6 import QtCore

ORGANISATION = APPLICATION = "labbench"


def open_settings(path=None) -> QtCore.QSettings:
    if path is not None:
        return QtCore.QSettings(str(path), QtCore.QSettings.Format.IniFormat)
    return QtCore.QSettings(QtCore.QSettings.Format.IniFormat, QtCore.QSettings.Scope.UserScope,
                            ORGANISATION, APPLICATION)


def remembered_paths(settings: QtCore.QSettings, rig: str | None, sessions: str | None,
                     default_sessions: str) -> tuple[str | None, str]:
    """The rig file and sessions folder to open: the ones given, else the last used (a rig
    file only while it still exists), else the built-in rig and ``default_sessions``."""
    if rig is None:
        last = settings.value("rig/file", "", type=str)
        rig = last if last and Path(last).is_file() else None
    if sessions is None:
        sessions = settings.value("sessions/folder", "", type=str) or default_sessions
    return rig, sessions


def save_protocol(settings: QtCore.QSettings, name: str, values: dict) -> None:
    """The settings of protocol ``name`` as the user left them (JSON: numbers, text, lists)."""
    settings.setValue(f"protocols/{name}", json.dumps(values))


def load_protocol(settings: QtCore.QSettings, name: str) -> dict:
    """The remembered settings of protocol ``name`` ({} when none or unreadable)."""
    text = settings.value(f"protocols/{name}", "", type=str)
    try:
        values = json.loads(text) if text else {}
    except ValueError:
        return {}
    return values if isinstance(values, dict) else {}
