"""Device panel (rig file, backend, the link to choose, connect, enable, state, stream
health) and the E-STOP button.

What the chosen backend needs from the person is on the panel itself: a serial board's
port (pyserial's list of the ports there are, or one typed in), a CANopen drive's CAN
interface and channel (python-can's ``detect_available_configs``, or the rig file's and
python-can's own configuration); a simulator says what it simulates. Every row has a
fixed height, so nothing below it moves when a backend or a state changes.

Compact, so that at 1280 x 800 (where the panel shares the left column with the Protocol
panel) the backend, Connect, the device and its health show without scrolling: one line
for the rig, the link and the device (the rest in their tooltips), the health in two
columns, shown only while a device is open; the timing check only while none is (it opens
the device itself).
"""
from __future__ import annotations

import threading

from PySide6 import QtCore, QtWidgets

from labbench.gui.labels import Elided, fixed_lines, set_text
from labbench.gui.worker import Mailbox
from labbench.registry import device_names

HEALTH_FIELDS = (("state", "state"), ("drops", "drops"), ("link", "link"), ("fault", "fault"))
HEALTH_TIPS = {"drops": "samples lost (sequence gaps)", "link": "the link's error counters"}
FROM_RIG = "as the rig file says"  # the link entry that passes nothing: the rig's own table
SIMULATED = {
    "sim": "simulated joint in the acquisition process (no hardware)",
    "sim-canopen": "simulated CiA 402 drive over a simulated CAN bus (no hardware)",
    "sim-serial": "simulated serial board over a pseudo-terminal (no hardware)",
    "avr-sim": "the board's firmware on an emulated AVR (no hardware)",
}


def health_text(value) -> str:
    """A health field as a person reads it: a dict of counters as "bad frames 0, lost 2"."""
    if isinstance(value, dict):
        return ", ".join(f"{str(k).replace('_', ' ')} {v}" for k, v in value.items()) or "none"
    return str(value)


def serial_ports() -> list[tuple[str, str]]:
    """(device, description) of the serial ports there are (pyserial's list)."""
    from serial.tools import list_ports

    return [(p.device, p.description) for p in sorted(list_ports.comports(), key=lambda p: p.device)]


def can_configs() -> list[dict]:
    """The CAN interfaces and channels python-can finds (``detect_available_configs``: it
    imports every interface module; seconds, so off the GUI thread); its notes about the
    ones not installed are not the person's business here."""
    import logging

    import can

    quiet = logging.getLogger("can")
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        return [dict(c) for c in can.detect_available_configs()]
    finally:
        quiet.setLevel(level)


class DevicePanel(QtWidgets.QGroupBox):
    """Buttons emit requests; the window does the work and reports back with ``set_*``."""

    connect_requested = QtCore.Signal(str)
    disconnect_requested = QtCore.Signal()
    enable_requested = QtCore.Signal(bool)
    rig_file_requested = QtCore.Signal(str)  # a rig file the person chose to load
    timing_requested = QtCore.Signal(str)  # the timing preflight on this backend

    def __init__(self, default_device: str = "sim", parent=None):
        super().__init__("Device", parent)
        self.rig_label = Elided()
        self.rig_button = QtWidgets.QPushButton("Rig file...")
        self.rig_button.setToolTip("load a rig file (TOML): the device's geometry, limits, link "
                                   "and commissioning; Write on the Commissioning page updates it")
        self.rig_button.clicked.connect(self._choose_rig)
        self.backend = QtWidgets.QComboBox()
        self.backend.addItems(device_names())
        self.backend.setCurrentText(default_device)
        self.backend.setToolTip("device backend; a rig file with a [canopen] or [serial] table selects it")
        self.connect_button = QtWidgets.QPushButton("Connect")
        self.enable_button = QtWidgets.QPushButton("Enable")
        self.enable_button.setEnabled(False)

        # the link row: one page per kind of backend, all of one height
        self.port = QtWidgets.QComboBox()
        self.port.setEditable(True)  # a port not listed (a pty, a pyserial URL) may be typed
        self.port.lineEdit().setPlaceholderText("serial port, e.g. /dev/ttyACM0")
        self.port.setToolTip("the board's serial port: pick one found, or type a device path or "
                             "a pyserial URL")
        self.interface = QtWidgets.QComboBox()
        self.interface.setToolTip("the CAN interface and channel of the drive's bus (python-can)")
        self.interface.addItem(FROM_RIG, None)
        self.simulated = Elided()
        self.link = QtWidgets.QStackedWidget()
        self._pages = {}
        for kind, field in (("sim", self.simulated), ("serial", self.port), ("canopen", self.interface)):
            page = QtWidgets.QWidget()
            row = QtWidgets.QHBoxLayout(page)
            row.setContentsMargins(0, 0, 0, 0)
            row.addWidget(field, 1)
            if kind != "sim":
                rescan = QtWidgets.QPushButton("\u21bb")
                rescan.setToolTip("look again for the ports / CAN interfaces there are")
                rescan.setFixedWidth(32)
                rescan.clicked.connect(lambda *_, k=kind: self.rescan(k))
                row.addWidget(rescan)
            self.link.addWidget(page)
            self._pages[kind] = page
        self.link.setFixedHeight(max(self.simulated.height(), self.port.sizeHint().height()))

        self.name_label = Elided("not connected", 2)
        # the health in two columns (state, drops / link, fault), one line each
        self.health = {key: Elided("-") for key, _ in HEALTH_FIELDS}
        self.health_grid = QtWidgets.QWidget()
        grid = QtWidgets.QGridLayout(self.health_grid)
        grid.setContentsMargins(0, 0, 0, 0)
        grid.setVerticalSpacing(2)
        for n, (key, title) in enumerate(HEALTH_FIELDS):
            name = QtWidgets.QLabel(title)
            name.setToolTip(HEALTH_TIPS.get(key, ""))
            grid.addWidget(name, n // 2, 2 * (n % 2))
            grid.addWidget(self.health[key], n // 2, 2 * (n % 2) + 1)
            grid.setColumnStretch(2 * (n % 2) + 1, 1)
        self.timing_button = QtWidgets.QPushButton("Check timing")
        self.timing_button.setToolTip(
            "the timing preflight (labbench devices --timing): the backend opened paced for "
            "the rig's [preflight] seconds, the loop's own calls; whether this PC and bus hold "
            "the rig's stale limit and sample time (the device must not be connected)")
        self.timing_label = Elided("not checked")  # the rest in its tooltip

        form = QtWidgets.QFormLayout(self)
        form.setContentsMargins(8, 4, 8, 4)
        form.setVerticalSpacing(3)
        row = QtWidgets.QHBoxLayout()
        row.addWidget(self.rig_label, 1)
        row.addWidget(self.rig_button)
        form.addRow("rig", row)
        row = QtWidgets.QHBoxLayout()
        row.addWidget(self.backend, 1)
        row.addWidget(self.connect_button)
        row.addWidget(self.enable_button)
        form.addRow("backend", row)
        self.link_title = QtWidgets.QLabel("link")
        form.addRow(self.link_title, self.link)
        form.addRow("device", self.name_label)
        # one row of one height: the timing check while no device is open, its health while one is
        self.timing_row = QtWidgets.QWidget()
        timing = QtWidgets.QHBoxLayout(self.timing_row)
        timing.setContentsMargins(0, 0, 0, 0)
        timing.addWidget(self.timing_button)
        timing.addWidget(self.timing_label, 1)
        self.status = QtWidgets.QStackedWidget()
        self.status.addWidget(self.timing_row)
        self.status.addWidget(self.health_grid)
        self.status.setFixedHeight(max(w.sizeHint().height() for w in (self.timing_row, self.health_grid)))
        self.status_title = QtWidgets.QLabel("timing")
        form.addRow(self.status_title, self.status)

        self._link = "none"
        self._activity = "idle"
        self._checking = False
        self.enabled = False
        self._scanned: set[str] = set()
        self._found = Mailbox()  # what a scan found, from its thread (no Qt call there)
        self._scans = 0  # scans under way
        self._poll = QtCore.QTimer(self)
        self._poll.setInterval(100)
        self._poll.timeout.connect(self._drain)
        self.connect_button.clicked.connect(self._on_connect)
        self.enable_button.clicked.connect(lambda: self.enable_requested.emit(not self.enabled))
        self.timing_button.clicked.connect(
            lambda: self.timing_requested.emit(self.backend.currentText()))
        self.backend.currentTextChanged.connect(self._backend_shown)
        self._backend_shown(self.backend.currentText())
        self._follow()

    # ----- the rig file, the link --------------------------------------------------------------
    def show_rig(self, rig, where: str) -> None:
        """The rig the window uses and where it came from (its file, or none loaded); the
        link row starts from the rig's own [serial] port."""
        set_text(self.rig_label, f"{rig.name}: {where}")
        port = rig.section("serial").get("port")
        if isinstance(port, str) and port and self.port.findText(port) < 0:
            self.port.insertItem(0, port)
        if isinstance(port, str) and port:
            self.port.setCurrentText(port)

    def _choose_rig(self) -> None:
        from labbench.gui.dialogs import choose_file

        path = choose_file(self, "Rig file (TOML)", "", "rig file (*.toml);;any file (*)")
        if path:
            self.rig_file_requested.emit(path)

    def _backend_shown(self, name: str) -> None:
        kind = name if name in ("serial", "canopen") else "sim"
        self.link.setCurrentWidget(self._pages[kind])
        self.link_title.setText({"serial": "port", "canopen": "CAN bus"}.get(kind, "link"))
        what = SIMULATED.get(name, "")
        set_text(self.simulated, what or f"{name}: a plug-in backend (its own settings in the rig file)")
        if kind != "sim" and kind not in self._scanned:
            self.rescan(kind)

    def rescan(self, kind: str) -> None:
        """Look for the serial ports or CAN interfaces there are, off the GUI thread."""
        self._scanned.add(kind)
        find = serial_ports if kind == "serial" else can_configs

        def job():
            try:
                found = find()
            except Exception as exc:  # noqa: BLE001 - a scan that fails is said, not raised
                found = exc
            self._found.put(kind, found)

        (self.port if kind == "serial" else self.interface).setToolTip("looking ...")
        self._scans += 1
        threading.Thread(target=job, name=f"labbench-scan-{kind}", daemon=True).start()
        self._poll.start()

    def _drain(self) -> None:
        for kind, found in self._found.drain():
            self._scans -= 1
            self._fill(kind, found)
        if not self._scans:
            self._poll.stop()

    def _fill(self, kind: str, found) -> None:
        combo = self.port if kind == "serial" else self.interface
        if isinstance(found, Exception):
            combo.setToolTip(f"could not look for them: {found}")
            return
        chosen = combo.currentText()
        combo.blockSignals(True)
        if kind == "serial":
            for device, description in found:
                if combo.findText(device) < 0:
                    combo.addItem(device)
                    combo.setItemData(combo.count() - 1, description, QtCore.Qt.ItemDataRole.ToolTipRole)
            combo.setToolTip(f"{len(found)} serial ports found; a path or pyserial URL may be typed")
        else:
            while combo.count() > 1:
                combo.removeItem(1)
            from labbench.drivers.canopen_config import SOFTWARE_BUSES

            for config in found:
                soft = " (software bus, no adapter)" if config.get("interface") in SOFTWARE_BUSES else ""
                combo.addItem(f"{config.get('interface')}: {config.get('channel')}{soft}", config)
            combo.setToolTip(f"{len(found)} CAN interfaces found by python-can; "
                             f"'{FROM_RIG}': the rig's [canopen] or python-can's own configuration")
        index = combo.findText(chosen)
        combo.setCurrentIndex(index if index >= 0 else 0)
        if kind == "serial" and index < 0:
            combo.setCurrentText(chosen)
        combo.blockSignals(False)

    def link_choice(self) -> dict:
        """What the person chose for the link of the backend shown: {"port": ...} for a
        serial board, {"interface": ..., "channel": ...} for a CAN bus, {} for the rig's own."""
        name = self.backend.currentText()
        if name == "serial":
            port = self.port.currentText().strip()
            return {"port": port} if port else {}
        if name == "canopen":
            config = self.interface.currentData()
            return {k: config[k] for k in ("interface", "channel") if config.get(k)} if config else {}
        return {}

    # ----- the run's state ---------------------------------------------------------------------
    def _on_connect(self):
        if self._link == "none":
            self.connect_requested.emit(self.backend.currentText())
        else:
            self.disconnect_requested.emit()

    def follow(self, state) -> None:
        """The run's state (``RunState``): Connect with no device, Disconnect with one (a
        latched one too: that clears the latch), the backend, link and rig fixed while one
        is open, Enable only on a connected device that no E-STOP latched."""
        self._link, self._activity = state.link, state.activity
        self._follow()

    def _follow(self) -> None:
        """The buttons as the link and a timing check in progress allow: the check opens
        the device itself, so it runs only with none connected, and nothing connects
        meanwhile."""
        link, checking = self._link, self._checking
        self.connect_button.setEnabled(link != "connecting" and not checking)
        self.connect_button.setText({"none": "Connect", "connecting": "Connecting..."}.get(
            link, "Disconnect"))
        free = link == "none" and not checking
        for w in (self.backend, self.link, self.rig_button):
            w.setEnabled(free and self._activity != "running")
        self.enable_button.setEnabled(link == "connected")
        self.timing_button.setEnabled(free)
        self.timing_button.setText("Checking..." if checking else "Check timing")
        open_ = link != "none"
        self.status.setCurrentWidget(self.health_grid if open_ else self.timing_row)
        self.status_title.setText("health" if open_ else "timing")

    def set_checking(self, checking: bool) -> None:
        self._checking = checking
        if checking:
            set_text(self.timing_label, "measuring ...")
        self._follow()

    def show_timing(self, result: dict | None, lines: list[str] = ()) -> None:
        """The preflight's verdict in one line (``labbench.loop.preflight.judge``: level and what to
        change), every figure in the tooltip; None: not checked."""
        if result is None:
            set_text(self.timing_label, "not checked")
            return
        level = result["verdict"]["level"]
        change = ", ".join(f"{k} = {v:g}" for t in result.get("rig_changes", {}).values()
                           for k, v in t.items())
        self.timing_label.setText(f"{level}: " + (f"set {change}" if change else
                                                  "the rig's limits hold" if level == "ok"
                                                  else "see the tooltip"))
        self.timing_label.setToolTip("\n".join(lines) or result.get("line", ""))

    def set_connected(self, description=None) -> None:
        """``description``: a DeviceDescription, or None when disconnected (or failed)."""
        if description is None:
            set_text(self.name_label, "not connected")
            self.set_enabled(False)
            for lab in self.health.values():
                set_text(lab, "-")
        else:
            d = description
            self.name_label.setText(d.label())
            self.name_label.setToolTip(f"{d.label()}; T = {d.sample_time_s * 1e3:g} ms, "
                                       f"force limit {d.force_limit_n:g} N")

    def set_enabled(self, enabled: bool) -> None:
        self.enabled = enabled
        self.enable_button.setText("Disable" if enabled else "Enable")

    def set_health(self, health: dict) -> None:
        """Show whatever the backend reports under the known keys (others ignored)."""
        for key, _ in HEALTH_FIELDS:
            if key in health:
                set_text(self.health[key], health_text(health[key]))


class EStopButton(QtWidgets.QPushButton):
    """Big red E-STOP; shows whether a stop is latched."""

    def __init__(self, key_hint: str, parent=None):
        super().__init__(parent)
        self.key_hint = key_hint
        self.setSizePolicy(QtWidgets.QSizePolicy.Policy.Expanding, QtWidgets.QSizePolicy.Policy.Fixed)
        self.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)  # never steals the key from the window
        self.set_latched(True)  # the taller of the two faces sets the height, once
        self.setFixedHeight(max(64, self.sizeHint().height()))
        self.set_latched(False)

    def set_latched(self, latched: bool) -> None:
        """Latched: two shorter lines in a smaller face (the one-line 18 pt text was cut off
        at both ends in a 360-460 px panel); one height for both, so nothing below moves."""
        self.latched = latched
        if latched:
            self.setText("E-STOP LATCHED: force zeroed\nreconnect the device to clear")
            colour, size = "#7a0010", 13
        else:
            self.setText(f"E-STOP  ({self.key_hint})")
            colour, size = "#d00020", 18
        self.setStyleSheet(f"QPushButton {{ background: {colour}; color: white; font-size: {size}pt;"
                           " font-weight: bold; border-radius: 8px; padding: 6px 10px; }")
        self.ensurePolished()
        self.setMinimumWidth(self.sizeHint().width())
