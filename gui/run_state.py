"""The run's one state machine: what the device link and the window's activity are now.

Two parts, one owner (the main window): the **link** to the device (none, connecting,
connected, latched) and the **activity** of the window (idle, running, replay). Every
change goes through a method here, which refuses what the state does not allow with
one line a person can act on (``UserError``); pages only read the state and follow its
``changed`` signal, so no page can start, stop or re-target a run on another's behalf.

    link:      none --connect--> connecting --connected--> connected --E-STOP--> latched
               (connecting --failed--> none; any --disconnect/died--> none)
    activity:  idle --run (link connected)--> running --ended--> idle
               idle --replay--> replay --ended--> idle
    campaign:  off --campaign_started--> on --campaign_ended--> off; while on, only the
               campaign's own points run (Start and the pages' runs are refused)
"""
from __future__ import annotations

from PySide6 import QtCore

from labbench.errors import UserError

NONE, CONNECTING, CONNECTED, LATCHED = "none", "connecting", "connected", "latched"
IDLE, RUNNING, REPLAY = "idle", "running", "replay"
WORDS = {RUNNING: "run", REPLAY: "replay"}  # an activity in a sentence
LATCH_HINT = "E-STOP is latched: disconnect and reconnect the device to clear it"


class RunState(QtCore.QObject):
    """``link`` and ``activity`` with their transitions; ``changed`` after each change."""

    changed = QtCore.Signal()

    def __init__(self, parent=None):
        super().__init__(parent)
        self.link = NONE
        self.activity = IDLE
        self.start_when_connected = False  # Start pressed before the device was open
        self.stopping = False  # Stop or E-STOP pressed: the run or replay is ending
        self.campaign = False  # a campaign is under way (its points are the only runs)

    # ----- what pages read --------------------------------------------------------------------
    @property
    def name(self) -> str:
        """One word for the status bar: the activity while there is one, else the link."""
        if self.activity != IDLE:
            return self.activity
        if self.campaign:
            return "campaign"
        return {NONE: "idle"}.get(self.link, self.link)

    @property
    def latched(self) -> bool:
        return self.link == LATCHED

    @property
    def can_start(self) -> bool:
        """Start (a run, commissioning) may be pressed: nothing under way, no latch."""
        return (self.activity == IDLE and not self.start_when_connected and self.link != LATCHED
                and not self.campaign)

    @property
    def armed(self) -> bool:
        """E-STOP has something to stop: a device (being) connected, or a run or replay."""
        return self.link != NONE or self.activity != IDLE

    def why_not_start(self) -> str:
        """Why Start is refused now ("" when it is not)."""
        if self.activity != IDLE:
            return f"a {WORDS[self.activity]} is in progress; stop it first"
        if self.link == LATCHED:
            return LATCH_HINT
        if self.start_when_connected:
            return "waiting for the device to connect"
        if self.campaign:
            return "a campaign is in progress; stop it first"
        return ""

    # ----- transitions ------------------------------------------------------------------------
    def connecting(self) -> None:
        if self.activity == RUNNING:
            raise UserError("stop the run before connecting again")
        self._set(link=CONNECTING)

    def connected(self) -> None:
        self._set(link=CONNECTED)

    def disconnected(self) -> None:
        """The device closed, a connection failed, or its process died."""
        self.start_when_connected = False
        if self.activity == RUNNING:
            self.stopping = False
        self._set(link=NONE, activity=IDLE if self.activity == RUNNING else self.activity)

    def check_disconnect(self) -> None:
        if self.activity == RUNNING:
            raise UserError("stop the run before disconnecting")

    def check_start(self) -> None:
        if why := self.why_not_start():
            raise UserError(why)

    def wait_for_device(self) -> None:
        """Start pressed without a device: the run starts once it is connected."""
        self.start_when_connected = True
        self.changed.emit()

    def take_pending_start(self) -> bool:
        """Whether a Start waited for this connection (and forget it)."""
        pending, self.start_when_connected = self.start_when_connected, False
        return pending

    @property
    def can_stop(self) -> bool:
        return self.activity != IDLE and not self.stopping

    def run(self) -> None:
        if self.link != CONNECTED:
            raise UserError(LATCH_HINT if self.link == LATCHED else "connect a device first")
        if self.activity != IDLE:
            raise UserError(f"a {WORDS[self.activity]} is in progress; stop it first")
        self._set(activity=RUNNING)

    def replay(self) -> None:
        if self.activity != IDLE:
            raise UserError(f"a {WORDS[self.activity]} is in progress; stop it first")
        self._set(activity=REPLAY)

    def stop_requested(self) -> None:
        """Stop (or E-STOP) pressed during a run or replay: it ends by itself shortly."""
        if self.activity != IDLE:
            self.stopping = True
            self.changed.emit()

    def ended(self) -> None:
        self.stopping = False
        self._set(activity=IDLE)

    def campaign_started(self) -> None:
        self.check_start()
        self.campaign = True
        self.changed.emit()

    def campaign_ended(self) -> None:
        self.campaign = False
        self.changed.emit()

    def latch(self) -> None:
        """E-STOP: a device (being) connected latches; with none, nothing to latch."""
        if self.link in (CONNECTING, CONNECTED):
            self.start_when_connected = False
            self._set(link=LATCHED)

    def _set(self, link: str | None = None, activity: str | None = None) -> None:
        self.link = self.link if link is None else link
        self.activity = self.activity if activity is None else activity
        self.changed.emit()
