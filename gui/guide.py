"""The first-run path, on screen above the pages: connect, commission, identify, render and
measure, each step marked done or not from the rig's own state (a device connected, the
rig's direction check, its newest chirp-ID in the sessions folder, an ETFE of it), and one
line saying what to do next and where. A step's button only shows or chooses (the
Commissioning page, a protocol on the left); nothing starts until the person presses Start.
"""
from __future__ import annotations

from dataclasses import dataclass

from PySide6 import QtCore, QtWidgets

STEPS = (("connect", "1 Connect"), ("commission", "2 Commission"), ("identify", "3 Identify"),
         ("measure", "4 Render and measure"))
DONE, NEXT, LATER = "\u2713", "\u25b6", "\u2022"


@dataclass
class RigState:
    """What the path follows: the link, the rig's commissioning, its identification, its
    measurements."""

    connected: bool = False
    simulated: bool = True
    commissioned: str = ""  # when and where the direction check passed ("": never)
    identified: str = ""  # the session of the rig's newest chirp-ID ("": none)
    measured: bool = False  # an ETFE of this rig succeeded in the sessions folder


def hints(state: RigState) -> dict[str, tuple[bool, str]]:
    """step -> (done, what to do, or what was done)."""
    return {
        "connect": (state.connected, "choose the backend and press Connect in the Device panel "
                    "(left); Start also connects"),
        "commission": (bool(state.commissioned) or state.simulated,
                       "not needed on a simulator (the Commissioning tab runs it anyway)"
                       if state.simulated and not state.commissioned else
                       f"direction checked: {state.commissioned}" if state.commissioned else
                       "on the Commissioning tab: Run commissioning, then Write to rig file "
                       "(real hardware renders no spring or damper before it)"),
        "identify": (bool(state.identified),
                     f"identified in {state.identified}" if state.identified else
                     "choose chirp-id on the left and press Start: the plant m, b every "
                     "theory and pre-check then uses"),
        "measure": (state.measured, "choose etfe on the left, set the VE (K, B) and press "
                    "Start: the rendered impedance against its theory"),
    }


class Guide(QtWidgets.QWidget):
    """A row of step buttons and the next step's line; ``step_requested`` carries the step
    clicked (the window shows or chooses, never starts)."""

    step_requested = QtCore.Signal(str)

    def __init__(self, parent=None):
        super().__init__(parent)
        row = QtWidgets.QHBoxLayout(self)
        row.setContentsMargins(4, 2, 4, 2)
        self.buttons = {}
        for key, title in STEPS:
            b = QtWidgets.QPushButton(title)
            b.setFlat(True)
            b.clicked.connect(lambda *_, k=key: self.step_requested.emit(k))
            row.addWidget(b)
            self.buttons[key] = b
        self.line = QtWidgets.QLabel()
        self.line.setWordWrap(True)
        row.addWidget(self.line, 1)
        self.state = RigState()
        self.show_state(self.state)

    def show_state(self, state: RigState) -> None:
        self.state = state
        found = hints(state)
        upcoming = next((k for k, _ in STEPS if not found[k][0]), None)
        for key, title in STEPS:
            done, why = found[key]
            mark = DONE if done else NEXT if key == upcoming else LATER
            b = self.buttons[key]
            b.setText(f"{mark} {title}")
            b.setToolTip(why)
            b.setStyleSheet("QPushButton { font-weight: bold; }" if key == upcoming else "")
        if upcoming is None:
            self.line.setText("every step done on this rig: run again any step, or look at the "
                              "runs in the Sessions tab")
        else:
            self.line.setText(f"<b>next: {dict(STEPS)[upcoming][2:]}</b>: {found[upcoming][1]}")

    def next_step(self) -> str | None:
        found = hints(self.state)
        return next((k for k, _ in STEPS if not found[k][0]), None)
