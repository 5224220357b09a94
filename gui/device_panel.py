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

        form = QtWidgets.QFormLayout(self)
        row = QtWidgets.QHBoxLayout()
        row.addWidget(self.backend, 1)
        row.addWidget(self.connect_button)
        row.addWidget(self.enable_button)
        form.addRow("backend", row)
        form.addRow("device", self.name_label)
        for key, title in HEALTH_FIELDS:
            form.addRow(title, self.health[key])

        self._link = "none"
        self.enabled = False
        self.connect_button.clicked.connect(self._on_connect)
        self.enable_button.clicked.connect(lambda: self.enable_requested.emit(not self.enabled))

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
        self.connect_button.setEnabled(state.link != "connecting")
        self.connect_button.setText({"none": "Connect", "connecting": "Connecting..."}.get(
            state.link, "Disconnect"))
        self.backend.setEnabled(state.link == "none")
        self.enable_button.setEnabled(state.link == "connected")

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

