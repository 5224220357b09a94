"""Device panel (connect, enable, state, stream health) and the E-STOP button."""
from __future__ import annotations

from PySide6 import QtCore, QtWidgets

from labbench.registry import device_names

HEALTH_FIELDS = (("state", "state"), ("drops", "drops (seq gaps)"), ("link", "link counters"),
                 ("fault", "fault"))


class DevicePanel(QtWidgets.QGroupBox):
    """Buttons emit requests; the window does the work and reports back with ``set_*``."""

    connect_requested = QtCore.Signal(str)
    disconnect_requested = QtCore.Signal()
    enable_requested = QtCore.Signal(bool)
    timing_requested = QtCore.Signal(str)

    def __init__(self, default_device: str = "sim", parent=None):
        super().__init__("Device", parent)
        self.backend = QtWidgets.QComboBox()
        self.backend.addItems(device_names())
        self.backend.setCurrentText(default_device)
        self.backend.setToolTip("device backend; a rig file with a [canopen] or [serial] table selects it")
        self.connect_button = QtWidgets.QPushButton("Connect")
        self.enable_button = QtWidgets.QPushButton("Enable")
        self.enable_button.setEnabled(False)
        self.name_label = QtWidgets.QLabel("not connected")
        self.name_label.setWordWrap(True)
        self.health = {key: QtWidgets.QLabel("-") for key, _ in HEALTH_FIELDS}
        for lab in self.health.values():
            lab.setWordWrap(True)
        self.timing_button = QtWidgets.QPushButton("Check timing")
        self.timing_button.setToolTip(
            "the timing preflight (labbench devices --timing): the backend opened paced for "
            "the rig's [preflight] seconds, the loop's own calls; whether this PC and bus hold "
            "the rig's stale limit and sample time (the device must not be connected)")
        self.timing_label = QtWidgets.QLabel("not checked")  # one line; the rest in its tooltip

        form = QtWidgets.QFormLayout(self)
        row = QtWidgets.QHBoxLayout()
        row.addWidget(self.backend, 1)
        row.addWidget(self.connect_button)
        row.addWidget(self.enable_button)
        form.addRow("backend", row)
        form.addRow("device", self.name_label)
        for key, title in HEALTH_FIELDS:
            form.addRow(title, self.health[key])
        timing = QtWidgets.QHBoxLayout()
        timing.addWidget(self.timing_button)
        timing.addWidget(self.timing_label, 1)
        form.addRow("timing", timing)

        self._link = "none"
        self._checking = False
        self.enabled = False
        self.connect_button.clicked.connect(self._on_connect)
        self.enable_button.clicked.connect(lambda: self.enable_requested.emit(not self.enabled))
        self.timing_button.clicked.connect(
            lambda: self.timing_requested.emit(self.backend.currentText()))

    def _on_connect(self):
        if self._link == "none":
            self.connect_requested.emit(self.backend.currentText())
        else:
            self.disconnect_requested.emit()

    def follow(self, state) -> None:
        """The run's state (``RunState``): Connect with no device, Disconnect with one (a
        latched one too: that clears the latch), the backend fixed while one is open,
        Enable only on a connected device that no E-STOP latched."""
        self._link = state.link
        self._follow()

    def _follow(self) -> None:
        """The buttons as the link and a timing check in progress allow: the check opens
        the device itself, so it runs only with none connected, and nothing connects
        meanwhile."""
        link, checking = self._link, self._checking
        self.connect_button.setEnabled(link != "connecting" and not checking)
        self.connect_button.setText({"none": "Connect", "connecting": "Connecting..."}.get(
            link, "Disconnect"))
        self.backend.setEnabled(link == "none" and not checking)
        self.enable_button.setEnabled(link == "connected")
        self.timing_button.setEnabled(link == "none" and not checking)
        self.timing_button.setText("Checking..." if checking else "Check timing")

    def set_checking(self, checking: bool) -> None:
        self._checking = checking
        if checking:
            self.timing_label.setText("measuring ...")
            self.timing_label.setToolTip("")
        self._follow()

    def show_timing(self, result: dict | None, lines: list[str] = ()) -> None:
        """The preflight's verdict in one line (``labbench.preflight.judge``: level and what to
        change), every figure in the tooltip; None: not checked."""
        if result is None:
            self.timing_label.setText("not checked")
            self.timing_label.setToolTip("")
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
            self.name_label.setText("not connected")
            self.set_enabled(False)
            for lab in self.health.values():
                lab.setText("-")
        else:
            d = description
            self.name_label.setText(f"{d.name} ({d.kind}), T = {d.sample_time_s * 1e3:g} ms, "
                                    f"force limit {d.force_limit_n:g} N")

    def set_enabled(self, enabled: bool) -> None:
        self.enabled = enabled
        self.enable_button.setText("Disable" if enabled else "Enable")

    def set_health(self, health: dict) -> None:
        """Show whatever the backend reports under the known keys (others ignored)."""
        for key, _ in HEALTH_FIELDS:
            if key in health:
                self.health[key].setText(str(health[key]))


class EStopButton(QtWidgets.QPushButton):
    """Big red E-STOP; shows whether a stop is latched."""

    def __init__(self, key_hint: str, parent=None):
        super().__init__(parent)
        self.key_hint = key_hint
        self.setMinimumHeight(64)
        self.setSizePolicy(QtWidgets.QSizePolicy.Policy.Expanding, QtWidgets.QSizePolicy.Policy.Fixed)
        self.setFocusPolicy(QtCore.Qt.FocusPolicy.NoFocus)  # never steals the key from the window
        self.set_latched(False)

    def set_latched(self, latched: bool) -> None:
        """Latched: two shorter lines in a smaller face, the button as tall as they need (the
        one-line 18 pt text was cut off at both ends in a 360-460 px panel)."""
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
        self.setMinimumHeight(max(64, self.sizeHint().height()))
        self.setMinimumWidth(self.sizeHint().width())

