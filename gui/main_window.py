"""The main window: it wires the pages together and owns the run's one state machine.

Left: E-STOP, the Device panel and the Protocol panel; right: the pages (Live,
Identification, Commissioning, Sessions, Sweeps), each its own module with its own
state; below them the event log; the loop's health in the status bar. A page asks
(its signals) and shows (its methods); only this window starts, stops and routes: the
run's state (``labbench.gui.run_state.RunState``: the device link and the activity)
changes here and every page follows it, so no page can change another's choice.

The device and its runs live in the acquisition process (``labbench.gui.acquisition``:
the GUI thread's drawing must not hold the interpreter the 1 kHz loop needs); replays,
estimates and exports run on worker threads (``labbench.gui.worker``,
``labbench.gui.live_estimate``). The window only drains their mailbox from a QTimer
(<= 30 Hz) and redraws, so it never freezes and the acquisition loop never waits for it.
"""
from __future__ import annotations

import dataclasses
import functools
import logging
from html import escape
import threading
import time
from pathlib import Path

import numpy as np
from PySide6 import QtCore, QtGui, QtWidgets
from pyqtgraph.util.garbage_collector import GarbageCollector

from labbench.gui.acquisition import Acquisition
from labbench.gui.campaign_view import CampaignView, read_table
from labbench.gui.commission_view import PROTOCOL as COMMISSION, CommissionView, has_file, rig_where
from labbench.gui.design_view import DesignView
from labbench.gui.device_panel import DevicePanel, EStopButton
from labbench.gui.estop_keys import KEYS, RULE, EStopKeys, hint
from labbench.gui.event_log import EventLog
from labbench.gui.exports import export_in_child
from labbench.gui.guide import Guide, RigState
from labbench.gui.id_view import IdView
from labbench.gui.labels import fixed_lines
from labbench.gui.jobs import (catalogue, load_identification, plant_data, reanalyse_session,
                               timing_preflight, used_method)
from labbench.gui.live_view import LiveView
from labbench.gui.loop_status import LoopStatus
from labbench.gui.protocol_panel import ProtocolPanel, precheck_text, settings_rows
from labbench.gui.run_state import IDLE, REPLAY, RUNNING, RunState
from labbench.gui.sessions_view import SessionsView
from labbench.gui.sweep_view import SweepView
from labbench.gui.units_choice import UnitsChoice, parse_or_si, units_text
from labbench.gui.verdict_view import judged, rendered_line, result_lines
from labbench.gui.wheel_guard import WheelGuard
from labbench.gui.worker import Mailbox, describe_error, run_in_background, start_replay
from labbench.design.tradeoffs import device_for
from labbench.errors import UserError
from labbench.readout.numfmt import fmt
from labbench.readout.wording import plant_source, session_label
from labbench.records import EVENT, STOP
from labbench.loop.safety import OVERRUN, SEQ_GAP
from labbench.sessions.session_catalogue import OWN_PLANT, plant_options
from labbench.model.ve import Plant

log = logging.getLogger(__name__)

SIM_BACKENDS = ("sim", "sim-canopen", "sim-serial", "avr-sim")
# the commissioning gate's remedy in the window's own words (the CLI's names its options)
GATE_REMEDY = ("on the Commissioning tab, Run commissioning, then Write to rig file (or start "
               "the window with --skip-commissioning)")
NO_FILE_GATE_REMEDY = "load the rig's file with Rig file... on the Device panel first; then " + GATE_REMEDY
NO_CAN = ("no CAN interface chosen and none configured: choose the drive's CAN bus in the Device "
          "panel (the CAN bus list; \u21bb looks for adapters)")
NO_PORT = "choose the board's serial port in the Device panel (the port list; \u21bb looks again)"


DELAY_ORIGINS = {"rig": "the rig file's measured_td_s", "device": "declared by the device",
                 "given": "given", "none": "none known"}


def delay_text(delay: dict, final: bool) -> str:
    """The device delay a pre-check used, in a few words (its source is the tooltip's);
    ``final``: it is the one the run will use (else the device, not connected yet, may
    declare one of its own)."""
    ms = f"{1e3 * float(delay.get('s') or 0.0):g} ms"
    if final:
        return f"device delay {ms} ({DELAY_ORIGINS.get(delay.get('origin'), 'given')})"
    return (f"device delay {ms}: the device is not connected, a delay of its own is not known "
            "yet (Start checks again with it; Connect to see it here)")


def guarded(slot):
    """A slot that reports any exception in the window instead of raising into Qt."""

    @functools.wraps(slot)
    def wrapper(self, *args, **kwargs):
        try:
            return slot(self, *args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - the window must survive every user action
            if not isinstance(exc, UserError):
                log.exception("GUI action %s failed", slot.__name__)
            self.show_error(describe_error(exc))

    return wrapper


def default_backend(rig) -> str:
    """A rig file with a [canopen] or [serial] table selects that driver; else the simulator."""
    for name in ("canopen", "serial"):
        if rig.section(name):
            return name
    return "sim"


def panel_protocols() -> list[str]:
    """The protocols the Protocol panel offers: every registered one but those a page runs
    itself (commissioning has its own page, settings and Write)."""
    from labbench.registry import protocol_names

    return [name for name in protocol_names() if name != COMMISSION]


_GC: GarbageCollector | None = None


def _collect_garbage_in_gui_thread() -> None:
    """Python's cyclic GC may run in any thread (e.g. a report export drawing with
    matplotlib) and then finalise Qt objects there: seen here as a segfault and as a
    deadlock. pyqtgraph's GarbageCollector turns automatic collection off and collects
    from a timer in the GUI thread instead; one per process."""
    global _GC
    if _GC is None:
        _GC = GarbageCollector(interval=1.0)


FIRST_SIZE = (1600, 1000)  # a first window's size where the screen has the room (pictures: always)


class MainWindow(QtWidgets.QMainWindow):
    def __init__(self, rig, session_dir, backend: str | None = None, redraw_hz: float = 30.0,
                 estimate_period_s: float = 0.5, realtime: bool = True, settings=None,
                 units=None, skip_commissioning: bool = False):
        """``settings``: a QSettings (``labbench.gui.settings.open_settings``) the window
        restores its state from and saves it to on close; None: it remembers nothing.
        ``units``: display units (``labbench.readout.units.DisplayUnits``) instead of the remembered
        ones; ``skip_commissioning``: render springs on real hardware before the rig passed
        its direction check (``labbench.commissioning.gate``), as the CLI's option."""
        super().__init__()
        _collect_garbage_in_gui_thread()
        self.settings = settings
        self.skip_commissioning = skip_commissioning
        self.rig = rig
        self.session_dir = Path(session_dir)
        self.realtime = realtime
        self.identified: dict | None = None  # the newest chirp-ID of this rig: the plant runs use
        self._id_session_shown: str | None = None  # whose identification the page shows
        self._measured = False  # an ETFE of this rig succeeded in the sessions folder
        self.mailbox = Mailbox()
        self.acquisition = Acquisition(self.mailbox)
        self.state = RunState(self)
        self.device = None  # DeviceDescription of the device open in the acquisition process
        self.health: dict = {}  # its latest health report
        self.estop_confirmed = False  # the acquisition process has emergency-stopped the device
        self.stop_event = threading.Event()  # stops a replay
        self.session_path: str | None = None
        self.last_run = None  # RunResult of the last run
        self._run_started = time.monotonic()
        self._replay: threading.Thread | None = None
        self._device_used = False  # a run has used the connected device
        self._backend_connected = ""  # the backend name of the device connected
        self._pending_protocol: str | None = None  # what a Start waiting for the device runs
        self._progress_shown = 0.0  # monotonic time of the last progress shown
        self._progress = 0.0  # the fraction of the run or replay done
        self._halted = ""  # Stop or E-STOP pressed: what the progress line says until the end
        self._run_protocol: str | None = None  # the protocol of the run under way (or last)
        self._replay_path: str | None = None
        self._replay_length = 0  # samples in the session being replayed (0: not known yet)
        self._live_timing = False  # the acquisition process sends the loop's timing live
        self._reanalysis: threading.Event | None = None  # cancels the re-analysis under way
        self.campaign_plan = None  # labbench.campaign.plan.Plan of the spec opened
        self.campaign_table: Path | None = None  # its table folder
        self.campaign_stop = None  # StopRequest of the campaign under way
        self._points_left: int | None = None  # points the campaign may still start (None: all)
        self._campaign_spec: str | None = None  # the spec the plan was made of
        self._point = None  # the point running: (planned point, consumers, answer, Event)

        self.setWindowTitle(f"labbench: {rig.name}")
        # 1600 x 1000, or the screen's room: at 1280 x 800 that size put Start, the log and
        # half the plots off the screen (a remembered geometry still wins, _restore_state)
        self.resize(QtCore.QSize(*FIRST_SIZE).boundedTo(self.screen().availableGeometry().size()))
        remembered = settings.value("device/backend", "", type=str) if settings else ""
        self.wheel_guard = WheelGuard(self)  # before any widget: no value changes under the wheel
        self._build(backend or remembered or default_backend(rig))
        self._wire()
        self._restore_state()
        if units is not None:
            self.units_choice.set_units(units)

        self.redraw_timer = QtCore.QTimer(self)
        self.redraw_timer.setInterval(max(int(1000 / min(redraw_hz, 30.0)), 33))  # <= 30 Hz
        self.redraw_timer.timeout.connect(self._tick)
        self.redraw_timer.start()
        self.estimate_timer = QtCore.QTimer(self)
        self.estimate_timer.setInterval(int(estimate_period_s * 1000))  # >= 2 estimates per second
        self.estimate_timer.timeout.connect(self.live.estimate)
        self.estimate_timer.start()
        self.health_timer = QtCore.QTimer(self)
        self.health_timer.setInterval(500)
        self.health_timer.timeout.connect(self._poll_health)
        self.health_timer.start()

        # Esc and Space: E-STOP anywhere in the application while a device is connected
        self.estop_keys = EStopKeys(lambda: self.state.armed, self.emergency_stop, self)
        QtWidgets.QApplication.instance().focusChanged.connect(self._show_keys_rule)
        self._watching_focus = True  # until the window closes (closeEvent may come twice)
        QtGui.QShortcut(QtGui.QKeySequence.StandardKey.Quit, self).activated.connect(self.close)
        self.log.add("info", f"rig: {rig.name} ({rig_where(rig)}); sessions in {self.session_dir}")
        self._follow_state()
        self._rig_changed()
        self._show_overlay()  # the rig's nominal until the sessions folder is read
        self.refresh_sessions()

    def showEvent(self, event) -> None:  # noqa: N802 - Qt override
        super().showEvent(event)
        if not self._laid_out:
            self._laid_out = True
            self._lay_out()

    def resizeEvent(self, event) -> None:  # noqa: N802 - Qt override
        super().resizeEvent(event)
        if self._laid_out and not self._body_chosen:  # maximised: the left column grows too
            self._size_left_column()

    def _body_dragged(self, *_) -> None:
        self._body_chosen = True

    def _lay_out(self) -> None:
        """The first sizes for this window's size: the left column wider on a wide screen
        (440 px up to 1600, then 30 % of the rest, at most 560), the Device panel as tall
        as it needs but at most 45 % of the panels' height, the rest to the settings."""
        self._size_left_column()
        total = max(self.panels.height(), 300)
        device = min(self.device_panel.sizeHint().height(), int(0.45 * total))
        self.panels.setSizes([device, total - device])

    def _size_left_column(self) -> None:
        """440 px up to a 1600 px window, then 30 % of the rest, at most 560 (``_lay_out``)."""
        width = self.width()
        left = int(min(max(440 + 0.3 * (width - 1600), 440), 560))
        self.body.setSizes([left, max(width - left, 400)])

    @property
    def mode(self) -> str:
        """What the window is doing: "idle", "running" (a run) or "replay"."""
        return self.state.activity

    # ----- layout -------------------------------------------------------------------------
    def _build(self, backend: str):
        self.estop = EStopButton(KEYS)
        self.device_panel = DevicePanel(backend)
        self.protocol_panel = ProtocolPanel(panel_protocols(), self.settings)
        self.live = LiveView(self.rig)
        self.id_view = IdView()
        self.commission = CommissionView(self.settings)
        self.sessions = SessionsView(self.session_dir, estimators=self._estimators())
        self.sweeps = SweepView(self.session_dir)  # a re-run point's session goes with the runs
        self.campaign = CampaignView()
        self.design = DesignView(settings=self.settings)
        self.units_choice = UnitsChoice()
        self.log = EventLog()
        # one strip of fixed height above everything: the first-run path, or a failure's
        # red banner in its place (click to dismiss): nothing below moves when one shows
        self.guide = Guide()
        self.banner = QtWidgets.QLabel()
        self.banner.setWordWrap(True)
        self.banner.setStyleSheet("QLabel { background: #fde0e0; color: #7a0010; padding: 4px;"
                                  " border: 1px solid #b00020; font-weight: bold; }")
        self.banner.mousePressEvent = lambda e: self._new_action()
        self.strip = QtWidgets.QStackedWidget()
        self.strip.addWidget(self.guide)
        self.strip.addWidget(self.banner)
        self.strip.setFixedHeight(3 * QtGui.QFontMetrics(self.banner.font()).lineSpacing() + 14)

        # the panels scroll on a short screen (their rows keep their heights); E-STOP, the
        # E-STOP keys' rule, the pre-check, Start, Stop and the progress never do
        self.keys_hint = fixed_lines(QtWidgets.QLabel(), 2)  # the E-STOP keys' rule, as it holds now
        self.keys_hint.setToolTip(RULE)
        # the Device panel (scrolling on a short screen) above the Protocol panel (whose form
        # scrolls), with a splitter between them: at 1280 x 800 both show
        scroll = QtWidgets.QScrollArea()
        scroll.setWidgetResizable(True)
        scroll.setFrameShape(QtWidgets.QFrame.Shape.NoFrame)
        scroll.setHorizontalScrollBarPolicy(QtCore.Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        scroll.setWidget(self.device_panel)
        self.panels = QtWidgets.QSplitter(QtCore.Qt.Orientation.Vertical)
        self.panels.addWidget(scroll)
        self.panels.addWidget(self.protocol_panel)
        self.panels.setChildrenCollapsible(False)
        self.panels.setStretchFactor(1, 1)
        left = QtWidgets.QWidget()
        ll = QtWidgets.QVBoxLayout(left)
        ll.setContentsMargins(4, 4, 4, 4)
        ll.addWidget(self.estop)
        ll.addWidget(self.keys_hint)
        ll.addWidget(self.panels, 1)
        ll.addWidget(self.protocol_panel.run_box)
        left.setMinimumWidth(360)
        left.setMaximumWidth(600)  # a wide screen's room goes to the settings and the pre-check

        self.tabs = QtWidgets.QTabWidget()
        for page, title in ((self.live, "Live"), (self.id_view, "Identification"),
                            (self.commission, "Commissioning"), (self.sessions, "Sessions"),
                            (self.sweeps, "Sweeps"), (self.campaign, "Campaign"),
                            (self.design, "Design")):
            self.tabs.addTab(page, title)
        self.tabs.setCornerWidget(self.units_choice, QtCore.Qt.Corner.TopRightCorner)
        right = QtWidgets.QSplitter(QtCore.Qt.Orientation.Vertical)
        right.addWidget(self.tabs)
        right.addWidget(self.log)
        right.setSizes([820, 150])

        body = QtWidgets.QSplitter()
        body.addWidget(left)
        body.addWidget(right)
        body.setStretchFactor(1, 1)
        body.setSizes([440, 1160])  # room for the device's own description (resizeEvent: wider)
        self.splitters = {"live": self.live.splitter, "identification": self.id_view.splitter,
                          "log": right, "body": body, "panels": self.panels}
        self._laid_out = False  # the splitters sized to the window once (unless restored)
        # the left column's width follows the window's (maximised, resized) until the person
        # drags it: then theirs stands, remembered with the splitters
        self._body_chosen = False
        body.splitterMoved.connect(self._body_dragged)
        central = QtWidgets.QWidget()
        cl = QtWidgets.QVBoxLayout(central)
        cl.setContentsMargins(4, 4, 4, 4)
        cl.addWidget(self.strip)
        cl.addWidget(body, 1)
        self.setCentralWidget(central)
        self.body = body
        self.loop_status = LoopStatus(self.statusBar())

    def _wire(self) -> None:
        """Each page's requests to the window's actions; the run's state to every page."""
        self.state.changed.connect(self._follow_state)
        self.estop.clicked.connect(self.emergency_stop)
        self.device_panel.connect_requested.connect(self.connect_device)
        self.device_panel.disconnect_requested.connect(self.disconnect_device)
        self.device_panel.enable_requested.connect(self.enable_device)
        self.device_panel.timing_requested.connect(self.check_timing)
        self.device_panel.backend.currentTextChanged.connect(lambda *_: self._rig_changed())
        self.device_panel.rig_file_requested.connect(self.load_rig_file)
        self.guide.step_requested.connect(self._guide_step)
        self.protocol_panel.protocol_changed.connect(self._protocol_chosen)
        self.protocol_panel.settings_changed.connect(self.update_precheck)
        self.protocol_panel.start_requested.connect(self.start_protocol)
        self.protocol_panel.stop_requested.connect(self.stop_run)
        self.live.estimate_shown.connect(lambda _est: self._show_overlay())
        self.live.warning.connect(lambda text: self.log.add("warning", text))
        self.commission.run_requested.connect(self.start_commissioning)
        self.commission.write_requested.connect(self.write_rig_file)
        self.sessions.refresh_requested.connect(self.refresh_sessions)
        self.sessions.replay_requested.connect(self.replay)
        self.sessions.reanalyse_requested.connect(self.reanalyse)
        self.sessions.export_requested.connect(self.export)
        self.sessions.cancel_requested.connect(self.cancel_reanalysis)
        self.sweeps.session_requested.connect(lambda path: self.replay(path, None))
        self.campaign.open_requested.connect(self.open_campaign)
        self.campaign.start_requested.connect(self.start_campaign)
        self.campaign.stop_requested.connect(self.stop_campaign)
        self.campaign.session_requested.connect(lambda path: self.replay(path, None))
        self.units_choice.changed.connect(self.set_units)

    def _follow_state(self) -> None:
        """Every page shows the run's state as it is now."""
        state = self.state
        self.protocol_panel.follow(state)
        self.commission.follow(state)
        self.campaign.follow(state)
        self.device_panel.follow(state)
        self.sessions.follow(state)
        self.estop.set_latched(state.latched)
        self._show_keys_rule()
        self._follow_rig()
        self.loop_status.show_mode(state.name)

    def _show_keys_rule(self, *_focus) -> None:
        """The E-STOP keys' rule in the status bar, as it holds now and where the keyboard is."""
        self.keys_hint.setText(hint(self.state.armed))

    @staticmethod
    def _estimators() -> list[str]:
        try:
            from labbench.analysis.etfe import ESTIMATORS
            return ["default", *ESTIMATORS]  # default: the analysis' own
        except ImportError:
            return ["default"]

    # ----- messages -------------------------------------------------------------------------
    def show_error(self, text: str) -> None:
        """A clear message in the window (the banner, in the first-run path's place) and in
        the event log."""
        self.banner.setText(text)
        self.banner.setToolTip(f"{text}\n(click to dismiss)")
        self.strip.setCurrentWidget(self.banner)
        self.log.add("error", text)

    def _new_action(self) -> None:
        """A new user action: an earlier failure's banner is history now (the log keeps it)."""
        self.strip.setCurrentWidget(self.guide)

    # ----- the first-run path ------------------------------------------------------------------
    def _follow_rig(self) -> None:
        """The first-run path follows the rig: connected, commissioned, identified, measured."""
        self.guide.show_state(RigState(
            connected=self.state.link in ("connected", "latched"), simulated=self.simulated,
            commissioned=self.rig.direction_checked,
            identified=session_label(self.identified["session"]) if self.identified else "",
            measured=self._measured))
        self.design.set_device(device_for(self.rig, self.simulated, self.identified),
                               self.rig.sample_time_s)

    def _guide_step(self, step: str) -> None:
        """A step of the path clicked: it shows, or chooses what the person asked for
        (never starts a run)."""
        if step == "connect" and self.state.link == "none":
            self.connect_device(self.device_panel.backend.currentText())
        elif step == "commission":
            self.tabs.setCurrentWidget(self.commission)
        elif step in ("identify", "measure"):
            self.protocol_panel.choice.setCurrentText("chirp-id" if step == "identify" else "etfe")
            self.tabs.setCurrentWidget(self.live)

    def info(self, text: str) -> None:
        self.statusBar().showMessage(text, 8000)
        self.log.add("info", text)

    # ----- device ---------------------------------------------------------------------------
    @guarded
    def connect_device(self, backend: str, opener=None, rig=None, options: dict | None = None):
        """Open ``backend`` in the acquisition process (``opener(rig, **options)`` instead of the
        registry's factory when given: a picklable callable, e.g. for an injected fault);
        ``rig`` and ``options``: a campaign point's own (default the window's rig)."""
        self._new_action()
        from labbench.registry import open_device

        if rig is None:  # the window's rig, with the link chosen on the Device panel
            rig, options = self._device_rig(backend)
        else:
            options = {**({"realtime": self.realtime} if backend == "sim" else {}), **(options or {})}
        self.state.connecting()
        self.log.add("info", f"connecting to {backend} ...")
        self._backend_connected = backend
        self.device = None
        self.estop_confirmed = False
        self.health = {}
        self.device_panel.set_connected(None)
        self.acquisition.connect(opener or functools.partial(open_device, backend), rig, options)

    def _device_rig(self, backend: str):
        """(the rig, the factory's options) to open ``backend`` with: the link the person chose
        on the Device panel (a serial port, a CAN interface) over the rig file's."""
        choice = self.device_panel.link_choice()
        if backend == "serial":
            port = choice.get("port") or self.rig.section("serial").get("port")
            if not port:
                raise UserError(NO_PORT)
            return self.rig, {"port": port}
        if backend == "canopen" and choice:
            sections = {**self.rig.sections, "canopen": {**self.rig.section("canopen"), **choice}}
            return dataclasses.replace(self.rig, sections=sections), {}
        return self.rig, ({"realtime": self.realtime} if backend == "sim" else {})

    @guarded
    def disconnect_device(self):
        self._new_action()
        self.state.check_disconnect()
        was, self.device = self.device, None
        self.device_panel.set_connected(None)
        self.state.disconnected()  # the latch lives in the device being closed
        if was is not None:
            self.acquisition.send("disconnect")
        self.update_precheck()  # without the device's own delay now

    @guarded
    def check_timing(self, backend: str):
        """The timing preflight on ``backend`` (``gui.jobs.timing_preflight``): its verdict on
        the Device panel, its figures in the log. The device must not be connected (the
        check opens it)."""
        self._new_action()
        if self.state.link != "none":
            raise UserError("disconnect the device first: the timing check opens it itself")
        self.device_panel.set_checking(True)
        self.log.add("info", f"checking timing on {backend} (labbench devices --timing) ...")
        run_in_background(self.mailbox, "timing", timing_preflight, self.rig, backend)

    def _on_timing_done(self, result: dict):
        from labbench.loop.preflight import lines

        text = lines(result["preflight"], result)
        self.device_panel.set_checking(False)
        self.device_panel.show_timing(result, text)
        for line in text:
            self.log.add("info", line)

    @guarded
    def enable_device(self, on: bool):
        self._new_action()
        if self.device is None:
            raise UserError("connect a device first")
        self.acquisition.send("enable" if on else "disable", 1.0)

    @guarded
    def emergency_stop(self):
        """Zero force at once (device latches), stop any run or replay; never raises.

        Sets the shared event the acquisition process's e-stop thread is blocked on: that
        thread calls ``device.emergency_stop()`` and stops the run without waiting for
        the GUI or for the loop."""
        self.acquisition.emergency_stop()
        self.stop_event.set()
        if self.campaign_stop is not None:
            self.campaign_stop.set("emergency stop (E-STOP)")
        had_device = self.state.link != "none"
        if self.mode != IDLE:
            self._halt(f"E-STOP: force zeroed, {self._activity} stopped at {100 * self._progress:.0f} %")
        self.device_panel.set_enabled(False)
        self.state.latch()  # until a reconnect clears it
        self.log.add("warning", "E-STOP: force zeroed, run stopped" if had_device
                     else "E-STOP: no device connected; any run or replay stopped", show=True)

    def _poll_health(self):
        buf = self.live.buffer
        if self.device is not None:
            health = dict(self.health)
            if self.mode == RUNNING:
                health["drops"] = str(_count_flag(buf, SEQ_GAP))
            self.device_panel.set_health(health)
        if self.mode == REPLAY:  # no loop runs: what the recording's flags say
            self.loop_status.show_overruns(_count_flag(buf, OVERRUN))

    # ----- protocol ---------------------------------------------------------------------------
    def _protocol_chosen(self, _name: str) -> None:
        self._new_action()
        self.update_precheck()

    def protocol_values(self, name: str | None = None) -> tuple[dict, dict | None]:
        """The settings of protocol ``name`` (default: the Protocol panel's choice) as shown
        where it is set, and the identification they take their plant from: as ``labbench
        run --plant-from last-id``, a protocol with plant fields left empty uses the newest
        chirp-ID of this rig in the sessions folder (None: the rig's nominal, or the plant
        given)."""
        name = name or self.protocol_panel.name
        values = self.commission.values() if name == COMMISSION else self.protocol_panel.values()
        found = self.identified
        if (found is None or name in OWN_PLANT or "plant_m_kg" not in values
                or values.get("plant_m_kg") is not None or values.get("plant_b") is not None):
            return values, None
        return {**values, **plant_options(found, values)}, found

    def make_protocol(self, name: str | None = None):
        from labbench.registry import make_protocol

        name = name or self.protocol_panel.name
        return make_protocol(name, **self.protocol_values(name)[0])

    @property
    def simulated(self) -> bool:
        """The device connected (or, before a connection, the backend chosen) is a simulator."""
        backend = self._backend_connected if self.device is not None else \
            self.device_panel.backend.currentText()
        return backend in SIM_BACKENDS

    def checked_protocol(self, name: str | None = None):
        """The configured protocol and its pre-check report, as the runner will check them
        (``labbench.runner.checks``: the same plant, gate and device delay, the connected
        device's own included); UserError when refused: bad settings, an unstable VE, or a
        spring or damper on real hardware before the rig passed its direction check
        (``labbench.commissioning.gate``: the CLI's one line)."""
        from labbench.runner import checks

        protocol = self.make_protocol(name)
        _plant, _delay, rep = checks(
            protocol, self.rig, self.device, self.simulated, self.skip_commissioning,
            remedy=GATE_REMEDY if has_file(self.rig) else NO_FILE_GATE_REMEDY,
            where=rig_where(self.rig))
        return protocol, rep

    def update_precheck(self):
        """Boundary and margin of the configured VE, shown before Start: green only when it
        is the check the run will make (the device connected, or the rig's measured delay,
        which wins over a device's own); before that, grey and saying so."""
        try:
            _protocol, rep = self.checked_protocol()
        except UserError as exc:
            self.protocol_panel.set_precheck(f"pre-check: {exc}", False)
            return
        except Exception as exc:  # noqa: BLE001 - shown beside Start, never raised into Qt
            self.protocol_panel.set_precheck(f"pre-check failed: {describe_error(exc)}", False)
            return
        plant = rep.get("plant") or {}
        text = precheck_text(rep)
        if "m" in plant and "b" in plant:  # the plant it was checked on, and whence
            values, found = self.protocol_values()
            source = plant_source({"plant_from": found, "protocol": values})  # as the run's record will say
            text += f" (plant m = {fmt(plant['m'])} kg, b = {fmt(plant['b'])} N s/m, {source})"
        delay = rep.get("device_delay") or {}
        final = self.device is not None or delay.get("origin") in ("rig", "given")
        text += "; " + delay_text(delay, final)
        stable = bool(rep.get("stable", True))
        self.protocol_panel.set_precheck(text, stable if final or not stable else None,
                                         tip=delay.get("source", ""))

    @guarded
    def start_protocol(self, name: str | None = None):
        """Start protocol ``name`` (default: the Protocol panel's choice) with its settings
        as shown where they are set, connecting the device first if needed."""
        self._new_action()
        name = name or self.protocol_panel.name
        self.state.check_start()
        if name == self.protocol_panel.name:
            self.update_precheck()
        protocol, _rep = self.checked_protocol(name)  # refuse bad settings before touching the device
        backend = self.device_panel.backend.currentText()
        if self.device is not None and self._device_used and backend in SIM_BACKENDS:
            # A fresh simulator per run: every run starts from the same state, so seeded
            # runs repeat exactly. Connecting closes the old one.
            self.device = None
        if self.device is None:
            self.connect_device(backend)
            if self.state.link == "connecting":
                self._pending_protocol = name
                self.state.wait_for_device()  # no second Start while the first waits
                self.protocol_panel.set_progress(0.0, f"connecting to {backend} ...")
            return
        values, plant_from = self.protocol_values(name)
        if plant_from:
            self.log.add("info", f"using m = {plant_from['m']:.5g} kg, b = "
                                 f"{plant_from['b']:.5g} N s/m identified in {plant_from['session']}")
        shown = self.commission.shown() if name == COMMISSION else self.protocol_panel.state()
        extra = {"gui_settings": shown}
        if plant_from:
            extra["plant_from"] = plant_from  # as labbench run records it
        if name == COMMISSION:
            self.commission.show_state("commissioning ...")
        else:  # its traces and, at its end, its verdicts (a Start pressed on another page ran unseen)
            self.tabs.setCurrentWidget(self.live)
        self._launch(protocol, values, self.rig, extra)

    def _launch(self, protocol, values: dict, rig, extra: dict):
        """Start ``protocol`` (made from ``values``) on the connected device: the one way a run
        leaves the window (a Start, commissioning, a campaign's point)."""
        self.live.reset()
        self.loop_status.clear()
        self.stop_event = threading.Event()
        self._device_used = True
        self._run_protocol, self.session_path = protocol.name, None
        self._progress, self._halted = 0.0, ""
        self._live_timing = False
        self._run_started = time.monotonic()
        self.state.run()
        self.protocol_panel.set_progress(0.0, "starting ...")
        self.log.add("info", f"start {protocol.name} with these settings:",
                     rows=settings_rows(protocol.config.as_dict()))
        self.acquisition.run(protocol.name, values, rig, self.session_dir, start_extra=extra,
                             simulated=self.simulated, skip_commissioning=self.skip_commissioning)

    @guarded
    def start_commissioning(self):
        """The Commissioning page's Run: the ``commission`` protocol with the page's own
        settings, through the same Start as any run (the Protocol panel's choice stays)."""
        self.start_protocol(COMMISSION)

    @guarded
    def write_rig_file(self):
        """``--write-rig``: the measured values of the last commissioning into the rig file
        (tomlkit, comments kept, FILE.bak first); the rig is read again, and a connected
        device is closed so that the next run opens it with the new file."""
        from labbench.commissioning import write_rig
        from labbench.rig import load_rig

        self._new_action()
        if self.mode != IDLE:
            raise UserError(f"a {self._activity} is in progress; write the rig file after it")
        fields = dict(self.commission.fields)
        if not fields:
            raise UserError("nothing to write: run commissioning first")
        path = str(self.rig.source)
        backup = write_rig(path, fields)
        self.rig = self.live.rig = load_rig(path)
        text = (f"{path}: wrote {', '.join(fields)} (old file {backup})" if backup
                else f"{path}: nothing to change")
        self.commission.show_written(text)
        self.log.add("info", text)
        if self.device is not None:
            self.disconnect_device()
            self.log.add("info", "the device is opened again with the new rig file at the next run")
        self._rig_changed()

    def _rig_changed(self) -> None:
        """The rig, or whether it is simulated, changed: the gate, the pages and the path follow."""
        self.commission.set_rig(self.rig, self.simulated)
        self.device_panel.show_rig(self.rig, rig_where(self.rig))
        self.setWindowTitle(f"labbench: {self.rig.name}")
        self.update_precheck()
        self._follow_rig()

    @guarded
    def load_rig_file(self, path: str) -> None:
        """A rig file the person chose on the Device panel replaces the rig (no device open)."""
        from labbench.rig import load_rig

        self._new_action()
        if self.state.link != "none":
            raise UserError("disconnect the device before loading another rig file")
        self.rig = self.live.rig = load_rig(path)
        self.identified = None
        self.log.add("info", f"rig: {self.rig.name} ({rig_where(self.rig)})")
        self._rig_changed()
        self.refresh_sessions()  # this rig's newest chirp-ID, its ETFE runs

    def set_units(self, units) -> None:
        """Display units (``labbench.readout.units.DisplayUnits``) of every plot and label at once."""
        self.live.set_units(units)
        self.id_view.set_units(units)
        self.design.set_units(units)

    @guarded
    def stop_run(self):
        if self.mode != IDLE:
            self.stop_event.set()
            self.acquisition.request_stop()
            self.log.add("info", f"stop requested ({self.mode})")
            self._halt(f"stopping the {self._activity} at {100 * self._progress:.0f} % ...")


    # ----- campaign -----------------------------------------------------------------------
    @guarded
    def open_campaign(self, path: str):
        """Plan the spec at ``path`` on the backend chosen, with the window's rig, the plant
        its runs use (the rig's newest chirp-ID, else its nominal) and the rig's last
        commissioning; the Campaign page shows the plan, or why there is none."""
        from labbench.campaign.plan import Context, commission_facts, describe, make_plan
        from labbench.rig import CampaignSettings
        from labbench.sweep import table as tables
        from labbench.sweep.spec import load_spec

        self._new_action()
        backend = self.device_panel.backend.currentText()
        found = self.identified
        try:
            plant = Plant(found["m"], found["b"]) if found else self.rig.nominal_plant
            context = Context(backend, self.rig, plant,
                              str(found["session"]) if found else "nominal",
                              self.simulated, CampaignSettings.from_rig(self.rig, self.simulated),
                              commission_facts(self.session_dir, self.rig.name),
                              self.skip_commissioning, found.get("coulomb_n") if found else None)
            plan = make_plan(load_spec(path), context)
        except UserError as exc:
            self.campaign_plan = None
            self.campaign.show_plan(None, str(exc))
            return
        table_dir = self.session_dir / "campaigns" / f"{Path(path).stem}-{backend}{tables.SUFFIX}"
        done = tables.done_keys(table_dir) if tables.is_table(table_dir) else set()
        self.campaign_plan, self.campaign_table = plan, table_dir
        self._campaign_spec = path
        self.campaign.show_plan(describe(plan, done, table_dir))
        self._show_campaign_table()

    @guarded
    def start_campaign(self):
        """Run the plan's points still to run, each through the same launch as a Start (on
        real hardware the plan is asked about once first)."""
        from labbench.campaign.engine import run_campaign
        from labbench.campaign.plan import describe
        from labbench.loop.interrupts import StopRequest

        self._new_action()
        if self.campaign_plan is None:
            raise UserError("open a campaign spec first")
        self.state.check_start()
        # planned again now: a chirp-ID or a commissioning run since the spec was opened is
        # what the points take and record (the plan said "no commissioning found" after one)
        self.open_campaign(self._campaign_spec)
        plan = self.campaign_plan
        if plan is None:
            return  # the plan no longer holds: the page says why
        if not plan.context.simulated:
            lines = describe(plan, set(), self.campaign_table)
            yes = QtWidgets.QMessageBox.question(
                self, "Start the campaign", "\n".join(lines) + "\n\nStart on real hardware?")
            if yes != QtWidgets.QMessageBox.StandardButton.Yes:
                return
        self.campaign_stop = StopRequest()
        self._points_left = self.campaign.limit.value() or None  # None: every point still to run
        self.state.campaign_started()
        self.campaign.set_running(True)
        self.campaign.show_state("starting ...")
        self.campaign_table.parent.mkdir(parents=True, exist_ok=True)
        self.log.add("info", f"campaign {plan.spec.name}: {len(plan.points)} points into "
                             f"{self.campaign_table}")
        run_in_background(self.mailbox, "campaign", run_campaign, plan, self.campaign_table,
                          self._campaign_point, self.campaign_stop,
                          progress=lambda p: self.mailbox.put("result", ("campaign_progress", p)))

    @guarded
    def stop_campaign(self):
        """Stop the campaign: the point running is stopped (it runs again next time)."""
        if self.campaign_stop is not None:
            self.campaign_stop.set("stopped in the window")
            self.campaign.show_state("stopping ...")
        if self.mode == RUNNING:
            self.stop_run()

    def _campaign_point(self, pp, stop, progress, consumers):
        """The campaign thread's point runner (``labbench.campaign.engine``): hands the point
        to the GUI thread, which connects the device with the point's rig and runs it, and
        waits for its (RunResult, session) or its failure."""
        from labbench.errors import DeviceError

        answer, done = {}, threading.Event()
        self.mailbox.put("result", ("campaign_point", (pp, consumers, answer, done)))
        done.wait()
        if "error" in answer:
            raise DeviceError(answer["error"])
        return answer["result"], answer["session"]

    def _on_campaign_point_done(self, point) -> None:
        pp, _consumers, answer, done = point
        self._point = point
        if self._points_left == 0 and self.campaign_stop is not None:  # as Stop: the rest next Start
            from labbench.gui.sweep_runner import limit_reached

            self.campaign_stop.set(limit_reached(self.campaign.limit.value()))
        if self.campaign_stop is None or self.campaign_stop.is_set():
            from labbench.runner import RunResult

            self._finish_point(result=RunResult("aborted", getattr(self.campaign_stop, "reason", "")
                                                or "campaign stopped"), session=None)
            return
        if self._points_left is not None:
            self._points_left -= 1
        self.campaign.show_state(f"point {pp.point.index + 1} of {len(self.campaign_plan.points)}: "
                                 f"{pp.label}")
        try:  # a fresh device per point, opened with the point's rig (as labbench campaign)
            self.connect_device(self.campaign_plan.context.device, rig=pp.rig,
                                options=pp.device_options)
        except Exception as exc:  # noqa: BLE001 - the campaign thread hears it
            self._finish_point(error=describe_error(exc))

    def _launch_point(self) -> None:
        from labbench.registry import make_protocol

        pp = self._point[0]
        try:
            protocol = make_protocol(pp.protocol_name, sample_time_s=pp.rig.sample_time_s,
                                     **pp.options)
            extra = {"campaign": {"name": self.campaign_plan.spec.name, "key": pp.key,
                                  "params": pp.point.params}}
            if pp.plant_from:
                extra["plant_from"] = pp.plant_from  # as labbench campaign records it
            self._launch(protocol, dict(pp.options), pp.rig, extra)
        except Exception as exc:  # noqa: BLE001 - the campaign thread hears it
            self._finish_point(error=describe_error(exc))

    def _finish_point(self, error: str | None = None, result=None, session=None) -> None:
        """The point's run is over (or could not start): the campaign thread goes on."""
        if self._point is None:
            return
        _pp, _consumers, answer, done = self._point
        self._point = None
        if error is not None:
            answer["error"] = error
        else:
            answer.update(result=result, session=session)
        done.set()

    def _on_campaign_progress_done(self, p) -> None:
        if p.phase == "done":
            self._show_campaign_table()
        eta = "" if p.eta_s is None else f", about {p.eta_s / 60:.1f} min left"
        self.campaign.show_state(f"{p.done} of {p.total} points; {p.point}: {p.message}{eta}")

    def _on_campaign_done(self, summary) -> None:
        why = getattr(self.campaign_stop, "reason", "")  # the window's own stop says why first
        state = "complete" if summary.complete else f"stopped: {why or summary.interrupted}"
        self._campaign_over(f"campaign {state}; {summary.ran} run now ({summary.rerun} again "
                            f"after an interruption), {summary.skipped} skipped, "
                            f"{summary.not_ok} not ok")

    def _campaign_over(self, line: str) -> None:
        self._finish_point(error="the campaign ended")
        self.campaign_stop = None
        self.state.campaign_ended()
        self.campaign.set_running(False)
        self.campaign.show_state(line)
        self.log.add("info", line)
        self._show_campaign_table()

    def _show_campaign_table(self) -> None:
        if self.campaign_table is not None:
            run_in_background(self.mailbox, "campaign_table", read_table, self.campaign_table)

    def _on_campaign_table_done(self, table) -> None:
        self.campaign.show_table(table)

    # ----- remembered state -----------------------------------------------------------------
    def _restore_state(self) -> None:
        s = self.settings
        if s is None:
            return
        for key, restore in (("window/geometry", self.restoreGeometry),
                             ("window/state", self.restoreState)):
            value = s.value(key)
            if isinstance(value, QtCore.QByteArray):
                restore(value)
        for name, splitter in self.splitters.items():
            value = s.value(f"splitters/{name}")
            if isinstance(value, QtCore.QByteArray) and splitter.restoreState(value):
                self._laid_out = True
        self._body_chosen = s.value("splitters/body_chosen", False, type=bool)
        self.tabs.setCurrentIndex(s.value("window/tab", 0, type=int))
        self.units_choice.set_units(parse_or_si(s.value("display/units", "", type=str)))

    def save_state(self) -> None:
        """Write what the window remembers (also done on close)."""
        s = self.settings
        if s is None:
            return
        s.setValue("window/geometry", self.saveGeometry())
        s.setValue("window/state", self.saveState())
        for name, splitter in self.splitters.items():
            s.setValue(f"splitters/{name}", splitter.saveState())
        s.setValue("splitters/body_chosen", self._body_chosen)
        s.setValue("window/tab", self.tabs.currentIndex())
        s.setValue("display/units", units_text(self.units_choice.units()))
        s.setValue("device/backend", self.device_panel.backend.currentText())
        self.protocol_panel.save_state()
        self.commission.save_state()
        if self.rig.source and Path(str(self.rig.source)).is_file():
            s.setValue("rig/file", str(Path(str(self.rig.source)).resolve()))
        s.setValue("sessions/folder", str(Path(self.sessions.directory).resolve()))
        s.sync()

    # ----- the redraw timer -------------------------------------------------------------------------
    def _tick(self):
        try:
            for kind, payload in self.mailbox.drain():
                self._handle(kind, payload)
            if self.mode == REPLAY and self._replay_length:
                self._show_progress(self.live.buffer.n / self._replay_length, "replay")
            self.live.redraw()
        except Exception as exc:  # noqa: BLE001 - a bad record must not stop the display
            log.exception("redraw failed")
            self.show_error(f"display error: {describe_error(exc)}")

    def _handle(self, kind: str, payload):
        if kind == "record":
            self.live.feed(payload)
            if self._point is not None and self.mode == RUNNING:
                for consume in self._point[1]:
                    consume(payload)
            if payload.get("kind") == EVENT:
                self.log.add("event", f"{payload.get('name')}: {payload.get('reason')}")
                if payload.get("name") == "segment" and self.mode == RUNNING:
                    self.device_panel.set_enabled(True)  # the loop enables the device for it
            elif payload.get("kind") == STOP:
                if self.mode == RUNNING:
                    self.device_panel.set_enabled(False)  # and disables it at the run's end
                self.log.add("info", f"stream stop: {payload.get('status')} {payload.get('reason', '')}")
        elif kind == "progress":
            if self.mode == RUNNING:
                self._show_progress(*payload)
        elif kind == "replay length":
            self._replay_length = payload
        elif kind == "reanalyse progress":
            if self._reanalysis is not None:  # not a late one from a cancelled job
                self.sessions.show_analysis(*payload)
        elif kind == "timing":
            self._live_timing = True
            self.loop_status.show_timing(payload, live=True)
        elif kind == "warning":
            self.log.add("warning", payload)
        elif kind == "session":
            self.session_path = payload
            self.log.add("info", f"recording to {payload}")
        elif kind == "result":
            tag, value = payload
            getattr(self, f"_on_{tag}_done", lambda v: None)(value)
        elif kind == "error":
            tag, message = payload
            self._on_error(tag, message)
        elif kind == "health":
            self.health = payload
        elif kind == "estopped":
            self.estop_confirmed = True
            self.log.add("warning", "E-STOP: device emergency-stopped by the acquisition process"
                         if payload else "E-STOP: acquisition process stopped, no device open",
                         show=True)
        elif kind == "acquisition died":
            self.device = None
            self.device_panel.set_connected(None)
            if self.mode == RUNNING:
                self._run_finished("run ended: the acquisition process died")
            self.state.disconnected()
            self.update_precheck()
            self._finish_point(error=f"the acquisition process ended (exit code {payload})")
            self.show_error(f"the acquisition process ended unexpectedly (exit code {payload}); "
                            "reconnect the device")

    def _show_progress(self, frac: float, text: str) -> None:
        """The progress bar and line of the run or replay under way (at most twice a second)."""
        if self.mode == IDLE or self._halted:
            return  # queued before the run ended or was stopped: the end state stays
        self._progress = frac
        now = time.monotonic()
        if now - self._progress_shown < 0.5 and frac < 1.0:
            return  # 2 Hz is plenty, and each update re-lays out the left panel
        self._progress_shown = now
        elapsed = now - self._run_started
        left = f"{elapsed * (1 - frac) / frac:.0f} s left" if 0.02 < frac < 1 else ""
        line = f"{text}: {100 * frac:.0f} %  {left}".strip()
        self.protocol_panel.set_progress(frac, line)
        if self._run_protocol == COMMISSION:
            self.commission.show_state(line)

    def _on_error(self, tag: str, message: str):
        if tag == "timing":
            self.device_panel.set_checking(False)
            self.device_panel.timing_label.setText("check failed: see the log")
        if tag == "reanalyse":
            cancelled = self._reanalysis is not None and self._reanalysis.is_set()
            self._reanalysis = None
            self.sessions.analysis_ended(
                "re-analysis cancelled: the window shows what it showed before" if cancelled
                else f"re-analysis failed: {message}", self.sessions.progress.value() / 1000)
            if cancelled:
                self.log.add("info", "re-analysis cancelled")
                return
        if tag == "connect":
            self.device_panel.set_connected(None)
            self.state.disconnected()
            if message.startswith("no CAN interface"):
                message = NO_CAN
        if tag in ("run", "replay"):
            self._run_finished(f"{tag} failed: {message}")
        if tag in ("connect", "run"):
            self._finish_point(error=f"{tag}: {message}")
        if tag == "export":
            self.sessions.export_ended(f"export failed: {message}")
        if tag == "campaign":
            self._campaign_over(f"campaign ended: {message}")
        self.show_error(f"{tag}: {message}")

    def _on_connect_done(self, desc):
        self.device = desc
        self._device_used = False
        self.device_panel.set_connected(desc)
        if self.state.link == "connecting":  # not latched by an E-STOP meanwhile
            self.state.connected()
        self._rig_changed()
        self.log.add("info", f"connected: {desc.name} ({desc.kind})")
        if self.state.take_pending_start():
            self.start_protocol(self._pending_protocol)
        elif self._point is not None and self.state.link == "connected":
            self._launch_point()

    def _on_disconnect_done(self, _):
        self.log.add("info", "disconnected")

    def _on_enable_done(self, _):
        self.device_panel.set_enabled(True)
        self.log.add("info", "device enabled")

    def _on_disable_done(self, _):
        self.device_panel.set_enabled(False)
        self.log.add("info", "device disabled")

    def _on_run_done(self, result):
        self.last_run = result
        status, reason = getattr(result, "status", "?"), getattr(result, "reason", "")
        level = "info" if status in ("success", "completed") else "warning"
        self.log.add(level, f"run ended: {status} {reason}".strip())
        if status not in ("success", "completed", "aborted"):
            self.show_error(f"run {status}: {reason}")
        self.loop_status.show_timing(getattr(result, "timing", {}) or {})
        self._show_results(getattr(result, "results", {}) or {}, self.session_path, self._run_protocol,
                           ran_here=status == "success")
        done = f"{100 * self._progress:.0f} %" if status != "success" else "100 %"
        self._run_finished(f"run {status} at {done}" + (f": {reason}" if status != "success" else ""))
        self.refresh_sessions()  # the run's session selected once the list has it
        self._finish_point(result=result, session=self.session_path)

    def _on_replay_done(self, status):
        from labbench.records import protocol_name

        self.log.add("info", f"replay {status}")
        buf = self.live.buffer
        if self._replay_length:  # all of it (completed), or as far as it went (stopped)
            self._progress = min(buf.n / self._replay_length, 1.0)
        timing = (buf.stop or {}).get("timing")
        if isinstance(timing, dict) and timing.get("periods"):  # what the run's status bar said
            self.loop_status.show_timing(timing, recorded=True)
        else:  # an older or cut-short record: what its samples' flags say
            self.loop_status.show_overruns(_count_flag(buf, OVERRUN))
        results = (buf.stop or {}).get("results")
        if isinstance(results, dict) and buf.start:
            self._show_results(results, self._replay_path, protocol_name(buf.start), replayed=True)
        self._run_finished(f"replay {status}")

    def _run_finished(self, line: str):
        """The run or replay is over; ``line``: what the progress line says of its end."""
        self._halted = ""
        self.protocol_panel.set_progress(self._progress, line)
        if self._run_protocol == COMMISSION and self.mode == RUNNING:
            self.commission.show_state(line)
        self.state.ended()
        self.live.invalidate_estimate()  # the final estimate, with the run's own estimator

    @property
    def _activity(self) -> str:
        return "run" if self.mode == RUNNING else self.mode

    def _halt(self, text: str) -> None:
        """Stop or E-STOP pressed: the progress line says so at once, and keeps saying it
        (progress still queued from the run is not shown); Stop cannot be pressed twice."""
        self._halted = text
        self.protocol_panel.set_progress(self._progress, text)
        self.state.stop_requested()

    # ----- results -------------------------------------------------------------------------
    def _show_results(self, results: dict, session: str | None, protocol: str | None,
                      ran_here: bool = False, replayed: bool = False):
        """A run's (or a replayed session's) results wherever the window shows a result:
        their verdicts on the Live page, an identification and a closed-loop fit on the
        Identification page, a commissioning on its page (``ran_here``: a run of this window
        on this rig, whose measured values may be written into the rig file)."""
        from labbench.readout import wording

        if results.get("error"):
            self.show_error(str(results["error"]))
        buf = self.live.buffer
        read = wording.of_results(protocol or "", results, buf.start or {})  # as the CLI, the report
        if read.rows:
            self.log.add("info", "results:", rows=read.row_texts(self.units_choice.units()))
        name = Path(session).name if session else "this run (not recorded)"
        self.live.verdicts.show_judged(read.verdicts, heading=f"<b>{escape(f'{protocol}, {name}')}</b>",
                                       lines=result_lines(read))
        ident = results.get("identification")
        if isinstance(ident, dict) and ident:
            from labbench.sessions.session_content import analysis_meta

            meta = analysis_meta(buf.start or {}, buf.descriptor or {})
            ahead = ((ran_here and protocol == "chirp-id")  # this rig's newest: the next runs'
                     or session == (self.identified or {}).get("session"))
            self.id_view.show_results(ident, plant_data(buf.snapshot(), meta),
                                      source=f"chirp-ID {name}",
                                      used=used_method(ident) if ahead else None)
            self._id_session_shown = session
            self.tabs.setCurrentWidget(self.id_view)
        if ran_here and protocol == "chirp-id" and session:
            self._identified_here(results, session)
        fit = results.get("loop_fit")
        if isinstance(fit, dict) and fit:
            self.id_view.show_loop_fit(fit, f"the run's own analysis of {name}, as its report: the "
                                       "run renders its VE, so the VE-path delay tv is its td; the "
                                       "device latency td is fitted")
        if protocol == COMMISSION:
            from datetime import datetime, timezone

            from labbench.commissioning import changes_to_write

            fields = {}
            if ran_here and session and "error" not in results:
                fields = changes_to_write(results, session,
                                          datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"))
            self.commission.show_result(results, session or "", fields)
            if replayed:
                self.commission.show_state(f"replayed: {name} (a run of this window, on this "
                                           "rig, writes the rig file; a replay does not)")
            self.tabs.setCurrentWidget(self.commission)

    # ----- sessions -------------------------------------------------------------------------
    @guarded
    def refresh_sessions(self):
        run_in_background(self.mailbox, "sessions", catalogue, self.sessions.directory,
                          self.session_dir, self.rig.name)

    @guarded
    def replay(self, path: str, speed):
        self._new_action()
        from labbench.sessions.session_format import looks_like_session

        if not looks_like_session(path):
            raise UserError(f"not a labbench session file: {path}")
        self.state.replay()
        self.live.reset()
        self.loop_status.clear("replay (no loop runs)")
        self.stop_event = threading.Event()
        self._replay_path, self._run_protocol = path, None
        self._progress, self._halted, self._replay_length = 0.0, "", 0
        self._run_started = time.monotonic()
        self.protocol_panel.set_progress(0.0, "replay: starting ...")
        self.tabs.setCurrentWidget(self.live)
        self.log.add("info", f"replay {Path(path).name} at {'1x' if speed == 1.0 else 'full speed'}")
        self._replay = start_replay(self.mailbox, path, speed, self.stop_event)

    @guarded
    def reanalyse(self, path: str, estimator: str):
        """``labbench analyze`` on a recorded session, on a worker thread, with its progress
        on the Sessions page and Cancel there (``labbench.analysis.progress``)."""
        self._new_action()
        if self._reanalysis is not None:
            raise UserError("a re-analysis is under way: wait for it or cancel it")
        name = Path(path).name
        self.log.add("info", f"re-analyse {name} with estimator {estimator}")
        fallback = self.rig.nominal_plant if self.live.uses_run_plant() else None
        self._reanalysis = threading.Event()
        self.sessions.show_analysis(0.0, f"re-analysing {name} ...")
        run_in_background(self.mailbox, "reanalyse", reanalyse_session, path,
                          None if estimator == "default" else estimator, fallback,
                          progress=lambda frac, phrase: self.mailbox.put(
                              "reanalyse progress", (frac, f"re-analysing {name}: {phrase}")),
                          cancel=self._reanalysis)

    def cancel_reanalysis(self) -> None:
        if self._reanalysis is not None:
            self._reanalysis.set()

    @guarded
    def export(self, path: str, fmt: str):
        self._new_action()
        out_dir = self.session_dir / "exports"
        out_dir.mkdir(parents=True, exist_ok=True)
        what = {"report": "a report (HTML and PDF: 10-30 s)"}.get(fmt, fmt)
        line = f"exporting {Path(path).name} as {what} into {out_dir} ..."
        self.log.add("info", line)
        self.sessions.show_export(line)  # a report took 24 s with nothing said meanwhile
        run_in_background(self.mailbox, "export", export_in_child, path, fmt, out_dir)

    def _on_reanalyse_done(self, value):
        """A re-analysis' results where they show; one that failed never replaces a good
        one silently: what was kept, and why, is said on the Live page and in the log."""
        est, id_results, data, again, record = value
        self._reanalysis = None
        name = Path(again["path"]).name
        kept = []  # what the re-analysis did not replace, and why
        if self.mode == IDLE:
            self.live.show_record(*record)  # its traces and axes, not the last record's
            if est is not None:
                self.live.show_estimate(est)
        else:
            kept.append(f"the Live page still shows the {self._activity} under way")
        good = {m: r for m, r in id_results.items() if "error" not in r}
        kept += [f"identification ({m}) failed: {r['error']}" for m, r in id_results.items()
                 if "error" in r]
        if good:
            self.id_view.show_results(good, data, source=f"re-analysis of {name}: "
                                      f"{' and '.join(good)} on the command force")
            self._id_session_shown = None
        fit = again.get("fit")
        shown = self.id_view.loop_fit
        if fit and "error" in fit and shown and "error" not in shown:
            kept.append(f"closed-loop fit failed: {fit['error']}; the fit shown is still "
                        f"the one of {self.id_view.fit_source.text()}")
        elif fit:
            self.id_view.show_loop_fit(fit, f"labbench analyze etfe --fit {again['options']}"
                                       f"{name}: the delay model chosen by cross-validation")
        read = again.get("readout")  # labbench analyze etfe's, as the CLI says it
        verdicts = list(read.verdicts) if read is not None else []
        verdicts += [j for m, r in good.items() for j in judged(f"identification ({m})", r.get("verdict"))]
        lines = rendered_line(read)
        lines += [(f"not replaced: {k}", "#a86b00") for k in kept]
        self.live.verdicts.show_judged(verdicts, heading=f"<b>re-analysis of {escape(name)}</b>",
                                       lines=lines)
        self.tabs.setCurrentWidget(self.live)
        for k in kept:
            self.log.add("warning", f"re-analysis of {name}: not replaced: {k}")
        self.log.add("info", "re-analysis done")
        self.sessions.analysis_ended(f"re-analysis of {name} done" + (
            f"; {len(kept)} result(s) not replaced (see the Live page)" if kept else ""), 1.0)

    def _on_export_done(self, paths):
        line = "exported: " + ", ".join(str(p) for p in paths)
        self.sessions.export_ended(line)
        self.info(line)

    def _on_sessions_done(self, value):
        summaries, found = value
        self.sessions.set_sessions(summaries)
        self._measured = any(s.protocol == "etfe" and s.status == "success"
                             and s.rig_name == self.rig.name for s in summaries)
        if self.session_path and self.mode == IDLE:  # the newest run of this window
            self.sessions.select_path(self.session_path)
        self._set_identified(found)

    # ----- the plant the next runs take ---------------------------------------------------------
    def _identified_here(self, results: dict, session: str) -> None:
        """A chirp-ID run of this window: the next run takes its plant at once (the sessions
        folder, read in the background, names the same one as ``last_identified``)."""
        from labbench.sessions.session_catalogue import identified_plant

        found = identified_plant(results, session)
        if found is not None:  # else not a plant last_identified would take either
            self._set_identified(found)

    def _set_identified(self, found: dict | None) -> None:
        """The newest chirp-ID of this rig (the plant the next runs' theory takes): the
        pre-check follows it, the Identification page shows it."""
        changed = (found or {}).get("session") != (self.identified or {}).get("session")
        self.identified = found
        if changed:
            self.update_precheck()
        self._follow_rig()
        if found and found["session"] != self._id_session_shown:
            self._id_session_shown = found["session"]
            run_in_background(self.mailbox, "identified", load_identification, found["session"])
        self._show_overlay()

    def _show_overlay(self) -> None:
        """The Identification page says which plant the theory overlay of the record shown
        uses, and whence, and which the next run takes (right after a chirp-ID they differ:
        its record's theory used the plant it ran with, the next run takes its fit; one line
        said the first above the column marked as the second)."""
        est = self.live.impedance.last
        if est is not None and est.theory:
            shown = f"m = {fmt(est.plant.m)} kg, b = {fmt(est.plant.b)} N s/m, {est.plant_source}"
        elif est is not None and est.plant is None:
            shown = "none: the plant could not be identified on this record"
        elif est is not None:
            shown = "none (the record renders no VE)"
        else:
            shown = None
        ahead = f"of the next run: {self._next_plant_text()}"
        self.id_view.show_overlay(ahead if shown is None else f"of the record shown: {shown}<br>{ahead}")

    def _next_plant_text(self) -> str:
        """The plant the next run's theory will use, and where it comes from."""
        if self.identified:
            f = self.identified
            return (f"m = {fmt(f['m'])} kg, b = {fmt(f['b'])} N s/m, identified in "
                    f"{session_label(f['session'])} (its l2 fit), unless its settings give m, b")
        p = self.rig.nominal_plant
        return f"m = {fmt(p.m)} kg, b = {fmt(p.b)} N s/m, the rig's nominal model"

    def _on_identified_done(self, value):
        ident, data, path = value
        if path != self._id_session_shown or not ident:
            return  # a newer one was asked for meanwhile
        self.id_view.show_results(ident, data, source=f"chirp-ID {Path(path).name}: this rig's "
                                  "newest, whose plant the next runs take", used=used_method(ident))

    # ----- shutdown -------------------------------------------------------------------------
    def closeEvent(self, event):
        self.estop_keys.remove()  # the application's filter: a closed window stops nothing
        if self._watching_focus:
            QtWidgets.QApplication.instance().focusChanged.disconnect(self._show_keys_rule)
            self._watching_focus = False
        self.wheel_guard.remove()
        self.save_state()
        self.stop_event.set()
        if self.campaign_stop is not None:
            self.campaign_stop.set("the window closed")
        self._finish_point(error="the window closed")
        for t in (self.redraw_timer, self.estimate_timer, self.health_timer):
            t.stop()
        if self._replay is not None:
            self._replay.join(timeout=3.0)
        # the runner zeroes the force and disables; then the device is closed and the child ends
        self.acquisition.shutdown(timeout=5.0)
        self.device = None
        self.sweeps.close_run()
        self.live.shutdown()
        super().closeEvent(event)


def _count_flag(buf, bit: int) -> int:
    """Samples of the stream whose loop flags carry ``bit`` (labbench.loop.safety)."""
    return int(np.count_nonzero(buf.channel("flags").astype(np.int64) & bit))

