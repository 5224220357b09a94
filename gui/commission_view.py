"""The commissioning page: walks a technician through ``labbench run commission`` on the
connected device (docs/commissioning.md) and writes what it measured into the rig file.

Each check (direction, delay, scale, friction, K_max) is a row: its verdict, its numbers
(``labbench.readout.wording``, as the report's summary and the CLI) and what to do
(the verdict's reasons, which name the ``[rig]`` field and its value). **Write to rig file**
is ``--write-rig``: the fields of ``labbench.commissioning.changes_to_write`` put into the
file with tomlkit (comments kept, ``FILE.bak`` first). The window runs the protocol through
the same acquisition process and runner as any other.
"""
from __future__ import annotations

from html import escape
from pathlib import Path

from PySide6 import QtCore, QtGui, QtWidgets

from labbench.gui.verdict_view import COLOURS

PROTOCOL = "commission"  # what the page runs (never the Protocol panel's choice)
CHECK_TITLES = {"direction": "1. direction", "delay": "2. delay", "scale": "3. scale",
                "friction": "4. friction and offset", "k_max": "5. stiffest safe spring K_max"}
COLUMNS = ("check", "verdict", "measured", "what to do")
STEPS = (
    "<b>Is the rig file true?</b> Before any spring or damper is rendered on a new rig, "
    "commissioning checks what the rig file believes: VE off, force doublets of both signs "
    "and a short chirp within the rig's force limit and position window (about 22 s of rig time).",
    "1. Connect the device (left). Leave the handle free to move.",
    "2. Press <b>Run commissioning</b>, with the settings under <b>settings</b> below (the "
    "<tt>commission</tt> protocol's; the Protocol panel on the left is for the measuring runs).",
    "3. Read each check below: a failed check says what is wrong and what to set.",
    "4. <b>Write to rig file</b> puts the measured values into the rig file (comments kept; the "
    "old file is kept as FILE.bak). A wrong scale is not written: the mass cannot tell whether "
    "the encoder or the lever arm is wrong; edit the one that is.",
    "5. Run again until the direction check passes and write again: the rig is then stamped "
    "<tt>direction_checked</tt>, and real hardware may render springs and dampers.",
)


NO_FILE = "no rig file loaded"


def has_file(rig) -> bool:
    """Whether ``rig`` was read from a file the page can write."""
    return bool(rig.source) and Path(str(rig.source)).is_file()


def rig_where(rig) -> str:
    """Where the window's rig comes from, for a person: its file, or none loaded (the
    built-in simulated rig's values)."""
    return str(rig.source) if has_file(rig) else f"built-in values ({NO_FILE})"


class CommissionView(QtWidgets.QWidget):
    """Buttons emit requests; the window runs, writes, and reports back with ``show_*``."""

    run_requested = QtCore.Signal()
    write_requested = QtCore.Signal()

    def __init__(self, settings=None, parent=None):
        """``settings``: a QSettings the page remembers its run's settings in (or None)."""
        super().__init__(parent)
        from labbench.gui.protocol_panel import protocol_form

        self.settings = settings
        self.form = protocol_form(PROTOCOL, settings)
        self.settings_box = QtWidgets.QGroupBox("settings (the commission protocol's)")
        self.settings_box.setCheckable(True)  # unticked: folded away
        self.settings_box.setChecked(False)
        QtWidgets.QVBoxLayout(self.settings_box).addWidget(self.form)
        self.form.setVisible(False)
        self.settings_box.toggled.connect(self.form.setVisible)
        steps = QtWidgets.QLabel("<br>".join(STEPS))
        steps.setWordWrap(True)
        self.rig_label = QtWidgets.QLabel()
        self.rig_label.setWordWrap(True)
        self.run_button = QtWidgets.QPushButton("Run commissioning")
        self.state = QtWidgets.QLabel("not run yet")
        self.state.setWordWrap(True)
        self.overall = QtWidgets.QLabel("")
        self.overall.setTextFormat(QtCore.Qt.TextFormat.RichText)
        self.table = QtWidgets.QTableWidget(0, len(COLUMNS))
        self.table.setHorizontalHeaderLabels(COLUMNS)
        self.table.verticalHeader().setVisible(False)
        header = self.table.horizontalHeader()
        for c in range(len(COLUMNS) - 1):
            header.setSectionResizeMode(c, QtWidgets.QHeaderView.ResizeMode.ResizeToContents)
        header.setSectionResizeMode(len(COLUMNS) - 1, QtWidgets.QHeaderView.ResizeMode.Stretch)
        self.table.setWordWrap(True)  # "what to do" wraps in its column
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.changes = QtWidgets.QLabel("")
        self.changes.setWordWrap(True)
        self.changes.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
        self.write_button = QtWidgets.QPushButton("Write to rig file")
        self.write_button.setEnabled(False)
        self.written = QtWidgets.QLabel("")
        self.written.setWordWrap(True)

        lay = QtWidgets.QVBoxLayout(self)
        lay.addWidget(steps)
        lay.addWidget(self.rig_label)
        lay.addWidget(self.settings_box)
        row = QtWidgets.QHBoxLayout()
        row.addWidget(self.run_button)
        row.addWidget(self.state, 1)
        lay.addLayout(row)
        lay.addWidget(self.overall)
        lay.addWidget(self.table, 1)
        lay.addWidget(self.changes)
        row = QtWidgets.QHBoxLayout()
        row.addWidget(self.write_button)
        row.addWidget(self.written, 1)
        lay.addLayout(row)

        self.results: dict = {}
        self.fields: dict = {}  # what Write puts into [rig]
        self._rig = None
        self._idle = True
        self.run_button.clicked.connect(self.run_requested)
        self.write_button.clicked.connect(self.write_requested)

    # ----- what the window tells the page --------------------------------------------------
    def set_rig(self, rig, simulated: bool) -> None:
        """The rig file the page would write, and whether the gate holds springs back."""
        self._rig = rig
        where = f"rig file <tt>{escape(str(rig.source))}</tt>" if has_file(rig) else (
            f"{NO_FILE}: nothing to write the results into (load one with <b>Rig file...</b> "
            "on the Device panel)")
        if rig.direction_checked:
            gate = f"direction checked: {escape(rig.direction_checked)}"
        elif simulated:
            gate = "not commissioned (a simulator renders springs anyway)"
        else:
            gate = ("<b>not commissioned</b>: on this real device the window renders no spring "
                    "or damper until the direction check has passed")
        self.rig_label.setText(f"{escape(rig.name)}: {where}; {gate}")
        self._sync_write()

    def values(self) -> dict:
        """The settings of the next commissioning run (UserError names a bad field)."""
        return self.form.values()

    def shown(self) -> dict:
        return self.form.shown()

    def save_state(self) -> None:
        from labbench.gui.protocol_panel import remember_form

        remember_form(self.settings, PROTOCOL, self.form)

    def follow(self, state) -> None:
        """The run's state (``RunState``): Run while a run may start, Write while idle."""
        self.run_button.setEnabled(state.can_start)
        self.run_button.setToolTip(state.why_not_start())
        self.form.setEnabled(state.activity == "idle")
        self._idle = state.activity == "idle"
        self._sync_write()

    def show_state(self, text: str) -> None:
        """What the run started from this page is doing (its progress line)."""
        self.state.setText(text)

    def show_result(self, results: dict, session: str, fields: dict) -> None:
        """A commissioning run's ``results`` (or {"error": ...}), recorded in ``session``;
        ``fields``: what writing the rig file would set (``changes_to_write``)."""
        from labbench.readout import wording
        from labbench.analysis.commission import CHECKS

        self.results, self.fields = results, dict(fields)
        self.written.setText("")
        name = Path(session).name if session else "not recorded"
        if "error" in results or "verdict" not in results:
            self.table.setRowCount(0)
            self.overall.setText("")
            self.state.setText(f"no result ({name}): {results.get('error', 'analysis missing')}")
            self._sync_write()
            return
        self.state.setText(f"result of {name}")
        level = str(results["verdict"].get("level"))
        bad = [CHECK_TITLES[c].split(". ", 1)[1] for c in CHECKS
               if ((results.get(c) or {}).get("verdict") or {}).get("level") not in (None, "ok")]
        self.overall.setText(f'<b style="color:{COLOURS.get(level, "#000")}">commissioning: {level}</b>'
                             + (f" ({escape(', '.join(bad))}: see what to do below)" if bad else
                                ": every check passed"))
        numbers = dict(wording.of_results("commission", results).row_texts())
        self.table.setRowCount(len(CHECKS))
        for r, check in enumerate(CHECKS):
            verdict = (results.get(check) or {}).get("verdict") or {}
            level = str(verdict.get("level", "-"))
            todo = "; ".join(verdict.get("reasons") or []) or "nothing to change"
            for c, text in enumerate((CHECK_TITLES[check], level, numbers[check], todo)):
                item = QtWidgets.QTableWidgetItem(text)
                item.setToolTip(text)
                if c == 1 and level in COLOURS:
                    item.setForeground(QtCore.Qt.GlobalColor.white)
                    item.setBackground(QtGui.QBrush(QtGui.QColor(COLOURS[level])))
                self.table.setItem(r, c, item)
        self.table.resizeRowsToContents()
        changes = results.get("changes") or {}
        text = ("rig changes: " + ", ".join(f"<tt>{k} = {escape(str(v))}</tt>" for k, v in changes.items())
                if changes else "rig changes: <b>nothing to change</b>")
        stamp = self.fields.get("direction_checked")
        writable = self._rig is not None and has_file(self._rig)
        if stamp:
            text += (f"; the direction passed: Write stamps <tt>direction_checked = {escape(stamp)}</tt>"
                     if writable else "; the direction passed")
        if not writable:
            text += f" ({NO_FILE}: nothing can be written; load one with <b>Rig file...</b> on the Device panel)"
        self.changes.setText(text)
        self._sync_write()

    def show_written(self, text: str) -> None:
        direction = (self.results.get("direction") or {}).get("verdict") or {}
        if direction.get("level") != "ok" and "direction_checked" not in self.fields:
            text += "; run commissioning again: the direction must pass before the rig is stamped"
        self.written.setText(text)
        self.fields = {}
        self._sync_write()

    def check_rows(self) -> dict[str, list[str]]:
        """check -> [verdict, measured, what to do] as shown (for tests)."""
        out = {}
        for r in range(self.table.rowCount()):
            out[self.table.item(r, 0).text()] = [self.table.item(r, c).text() for c in range(1, 4)]
        return out

    def _sync_write(self) -> None:
        can = self._rig is not None and has_file(self._rig) and bool(self.fields)
        self.write_button.setEnabled(can and self._idle)
        if self._rig is not None and not has_file(self._rig):
            self.write_button.setToolTip(f"{NO_FILE}: load one with Rig file... on the Device panel")
        elif not self.fields:
            self.write_button.setToolTip("nothing to write: run commissioning first")
        else:
            self.write_button.setToolTip("writes " + ", ".join(self.fields) + " into [rig]")

