"""The display units of the window, as the CLI's ``--units`` (``labbench.readout.units``): lengths in
m or mm, angles in rad or deg, frequencies in rad/s or Hz. Display only: settings, sessions
and exports stay SI."""
from __future__ import annotations

from PySide6 import QtCore, QtWidgets

from labbench.errors import UserError
from labbench.readout.units import UNITS, DisplayUnits

KINDS = ("length", "angle", "frequency")


def units_text(units: DisplayUnits) -> str:
    """``m,rad,Hz``: what ``DisplayUnits.parse`` reads back (and what the settings keep)."""
    return ",".join(getattr(units, kind) for kind in KINDS)


def parse_or_si(text: str | None) -> DisplayUnits:
    """Remembered units; SI when the text is not (any longer) a choice."""
    try:
        return DisplayUnits.parse(text)
    except UserError:
        return DisplayUnits()


class UnitsChoice(QtWidgets.QWidget):
    """Three drop-down lists, one per kind; ``changed`` carries the new DisplayUnits."""

    changed = QtCore.Signal(object)

    def __init__(self, units: DisplayUnits | None = None, parent=None):
        super().__init__(parent)
        lay = QtWidgets.QHBoxLayout(self)
        lay.setContentsMargins(4, 0, 4, 0)
        lay.addWidget(QtWidgets.QLabel("units:"))
        self.combos: dict[str, QtWidgets.QComboBox] = {}
        for kind in KINDS:
            combo = QtWidgets.QComboBox()
            combo.addItems([u for u, (k, _) in UNITS.items() if k == kind])
            combo.setToolTip(f"display unit of {kind}s (files and settings stay SI)")
            combo.currentTextChanged.connect(lambda *_: self.changed.emit(self.units()))
            lay.addWidget(combo)
            self.combos[kind] = combo
        self.set_units(units or DisplayUnits())

    def units(self) -> DisplayUnits:
        return DisplayUnits(**{kind: c.currentText() for kind, c in self.combos.items()})

    def set_units(self, units: DisplayUnits) -> None:
        """Show ``units`` (emits ``changed`` once if they differ)."""
        if units == self.units():
            return
        for kind, combo in self.combos.items():
            combo.blockSignals(True)
            combo.setCurrentText(getattr(units, kind))
            combo.blockSignals(False)
        self.changed.emit(self.units())
