"""Protocol panel: choice of protocol, its settings in a form, pre-check, Start/Stop, progress.

The form is built from the protocol's own validated config (``config.as_dict()``
of ``labbench.protocols.make_protocol(name)``), so new settings appear without GUI
changes; units and limits come from the name suffix convention of the project
(``_s``, ``_hz``, ``_n``, ``_m``...) and from the VE's fields. The protocol
validates the values itself when Start is pressed.
"""
from __future__ import annotations

import math
from html import escape

from PySide6 import QtCore, QtGui, QtWidgets

from labbench.errors import UserError
from labbench.gui.labels import fixed_lines, set_text
from labbench.readout.numfmt import fmt
from labbench.model.ve import VE_KINDS

# name or suffix -> (unit, lower limit); the protocol itself enforces the real bounds
UNITS = {
    "K": ("N/m", 0.0), "K_stop": ("N/m", 0.0), "B": ("N s/m", 0.0), "w0": ("rad/s", 1e-3), "T": ("s", 1e-6), "td": ("s", 0.0),
    "m": ("kg", 1e-6), "b": ("N s/m", 0.0), "plant_b": ("N s/m", 0.0), "_kg": ("kg", 0.0),
    "_s": ("s", 0.0), "_hz": ("Hz", 0.0), "_n": ("N", 0.0), "_m": ("m", 0.0), "_j": ("J", 0.0),
    "_rad_s": ("rad/s", 0.0), "_n_per_s": ("N/s", 0.0), "_m_s": ("m/s", 0.0),
    "plant_coulomb_ci95": ("N", 0.0),
}
# fields whose name does not read as words (an interval of two numbers)
WORDS = {"plant_coulomb_n": "plant Coulomb friction",
         "plant_coulomb_ci95": "plant Coulomb friction 95 % interval lo, hi"}
# optional fields that hold two numbers (lo, hi), not one
PAIRS = frozenset({"plant_coulomb_ci95"})
def choices() -> dict[str, list[str]]:
    """Text fields with a fixed set of values: shown as drop-down lists."""
    from labbench.protocols.excitation import SWEEPS
    from labbench.protocols.stability_probe import PROBE_KINDS, VARIABLES

    from labbench.analysis.identify import MODEL_CHOICES

    out = {"ve": list(dict.fromkeys([*VE_KINDS, *PROBE_KINDS])), "sweep": list(SWEEPS),
           "variable": list(VARIABLES), "model": list(MODEL_CHOICES)}
    try:
        from labbench.analysis.etfe import ESTIMATORS
        out["estimator"] = list(ESTIMATORS)
    except ImportError:  # the estimator field stays free text
        pass
    return out


def _unit(name: str):
    """(unit, lower limit, readable label) of a config field."""
    if name in UNITS:
        return (*UNITS[name], WORDS.get(name, name.replace("_", " ")))
    for suffix in sorted((k for k in UNITS if k.startswith("_")), key=len, reverse=True):
        if name.endswith(suffix):
            return (*UNITS[suffix], WORDS.get(name, name[: -len(suffix)].replace("_", " ")))
    return ("", None, WORDS.get(name, name.replace("_", " ")))


class Field:
    """One setting shown as a plain Qt widget: ``get`` parses what is shown (UserError on a
    bad number), ``set`` shows a value as ``get`` returns it (TypeError/ValueError when the
    field cannot hold it), ``shown`` is what a person sees (text, tick, choice)."""

    def __init__(self, name: str, value, lists: dict, help: str = "", whole: bool = False,
                 drawn: bool = False):
        """``help``: what the setting means (its tooltip, ``labbench.protocol.field_help``);
        ``whole``: an optional field that takes whole numbers; ``drawn``: left empty, the
        protocol draws it anew for each run and records it (a noise seed)."""
        self.name = name
        self.whole = whole
        self.unit, self.low, label = _unit(name)
        self.label = f"{label} [{self.unit}]" if self.unit else label
        if isinstance(value, bool):
            self.kind, self.widget = "bool", QtWidgets.QCheckBox()
        elif name in lists and (value is None or isinstance(value, str)):
            self.kind, self.widget = "choice", QtWidgets.QComboBox()
            if value is None:  # the protocol's default, kept as None
                self.widget.addItem("(default)", None)
            for option in lists[name]:
                self.widget.addItem(option, option)
        else:
            self.kind = ("int" if isinstance(value, int) else "float" if isinstance(value, float)
                         else "optional" if value is None else "text" if isinstance(value, str)
                         else "numbers")
            self.widget = QtWidgets.QLineEdit()
            if self.kind == "optional" and drawn:
                self.label += " (empty: new each run)"
                self.widget.setPlaceholderText("drawn anew for each run, recorded")
            elif self.kind == "optional":
                self.label += " (opt.)"
                self.widget.setPlaceholderText("default")
            self.widget.textChanged.connect(self._mark)
        self.widget.setToolTip(help or name if self.kind != "optional" or help
                               else f"{name}: empty = not set (default, or no filter for w0)")
        self.set(value)

    @staticmethod
    def editable(value) -> bool:
        """Whether a config value has a field."""
        return (value is None or isinstance(value, (bool, int, float, str))
                or (isinstance(value, (list, tuple)) and all(_is_number(v) for v in value)))

    def signal(self):
        """The widget's signal for an edit."""
        if self.kind == "bool":
            return self.widget.toggled
        return self.widget.currentIndexChanged if self.kind == "choice" else self.widget.textChanged

    def shown(self):
        if self.kind == "bool":
            return self.widget.isChecked()
        return self.widget.currentText() if self.kind == "choice" else self.widget.text()

    def get(self):
        if self.kind == "bool":
            return self.widget.isChecked()
        if self.kind == "choice":
            return self.widget.currentData()
        text = self.widget.text().strip()
        if self.kind == "text":
            return text
        if self.kind == "numbers":
            return [self._number(v.strip()) for v in text.split(",") if v.strip()]
        if self.kind == "optional" and not text:
            return None
        if self.name in PAIRS:
            pair = [self._number(v.strip()) for v in text.split(",")]
            if len(pair) != 2:
                raise UserError(f"{self.name}: {text!r} is not two numbers lo, hi")
            return pair
        return self._number(text)

    def set(self, value) -> None:
        if self.kind == "bool":
            if not isinstance(value, bool):
                raise TypeError(f"{self.name}: {value!r} is not true or false")
            self.widget.setChecked(value)
        elif self.kind == "choice":
            index = self.widget.findData(value) if value is None or isinstance(value, str) else -1
            if index < 0:
                raise ValueError(f"{self.name}: {value!r} is not one of its choices")
            self.widget.setCurrentIndex(index)
        elif self.kind == "text":
            if not isinstance(value, str):
                raise TypeError(f"{self.name}: {value!r} is not text")
            self.widget.setText(value)
        elif self.kind == "numbers":
            if not (isinstance(value, (list, tuple)) and all(_is_number(v) for v in value)):
                raise TypeError(f"{self.name}: {value!r} is not a list of numbers")
            self.widget.setText(", ".join(_number_text(v) for v in value))
        elif value is None and self.kind == "optional":
            self.widget.setText("")
        elif self.name in PAIRS and isinstance(value, (list, tuple)) and len(value) == 2 \
                and all(_is_number(v) for v in value):
            self.widget.setText(", ".join(_number_text(v) for v in value))
        elif not _is_number(value):
            raise TypeError(f"{self.name}: {value!r} is not a number")
        else:
            try:
                number = float(value)
            except OverflowError:
                raise ValueError(f"{self.name}: {value} is out of range") from None
            whole = self.kind == "int" or self.whole
            if whole and not number.is_integer():
                raise TypeError(f"{self.name}: {value!r} is not a whole number")
            self.widget.setText(_number_text(int(value) if whole else number))

    def _number(self, text: str):
        try:
            value = int(text) if self.kind == "int" or self.whole else float(text)
        except ValueError:
            whole = "whole " if self.kind == "int" or self.whole else ""
            raise UserError(f"{self.name}: {text!r} is not a {whole}number") from None
        if self.low is not None and value < self.low:
            raise UserError(f"{self.name}: {text} is below {self.low:g} {self.unit}")
        return value

    def _mark(self) -> None:
        """A red frame while the text is not a value the field takes."""
        try:
            self.get()
            bad = False
        except UserError:
            bad = True
        self.widget.setStyleSheet("QLineEdit { border: 2px solid #b00020; }" if bad else "")


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _number_text(value) -> str:
    """A number as a person types it, read back to the same value: whole numbers in full
    (a 64-bit seed), others in 12 digits when they hold it, else all of them."""
    if isinstance(value, int):
        return str(value)
    short = f"{value:.12g}"
    return short if float(short) == value else repr(value)


class SettingsForm(QtWidgets.QWidget):
    """The settings of one protocol, from its validated config (``config.as_dict()``), as a
    form of plain Qt fields; a value of another shape (a list of words) keeps its default."""

    changed = QtCore.Signal()

    def __init__(self, config: dict, parent=None, helps: dict | None = None,
                 whole: frozenset = frozenset(), drawn: frozenset = frozenset()):
        """``helps``: field -> what it means (tooltips); ``whole``: optional fields of whole
        numbers; ``drawn``: fields the protocol draws for each run when left empty."""
        super().__init__(parent)
        lists = choices()
        helps = helps or {}
        self.fields = {name: Field(name, value, lists, helps.get(name, ""), name in whole,
                                   name in drawn)
                       for name, value in config.items() if Field.editable(value)}
        form = QtWidgets.QFormLayout(self)
        form.setFieldGrowthPolicy(QtWidgets.QFormLayout.FieldGrowthPolicy.AllNonFixedFieldsGrow)
        for field in self.fields.values():
            field.signal().connect(lambda *_: self.changed.emit())
            form.addRow(field.label, field.widget)

    def values(self) -> dict:
        """Plain values (UserError names the first field that does not parse)."""
        return {name: field.get() for name, field in self.fields.items()}

    def shown(self) -> dict:
        """What each field shows, as a person reads it."""
        return {name: field.shown() for name, field in self.fields.items()}

    def apply(self, values: dict) -> None:
        """Show remembered ``values`` (as ``values()`` gave them); names the protocol no
        longer has, and values a field cannot hold, are left out."""
        for name, value in values.items():
            if name in self.fields:
                try:
                    self.fields[name].set(value)
                except (TypeError, ValueError):
                    continue  # a value of another type than the field now has


def settings_rows(config: dict, prefix: str = "") -> list[tuple[str, str]]:
    """(label with unit, value) per setting of a (nested) config, for a table a person reads
    (the run's start in the event log); a None is the protocol's default."""
    rows = []
    for name, value in config.items():
        unit, _low, label = _unit(name)
        if isinstance(value, dict):
            rows += settings_rows(value, f"{prefix}{label}: ")
            continue
        text = "default" if value is None else fmt(value, 6)
        rows.append((f"{prefix}{label}", f"{text} {unit}" if unit and value is not None else text))
    return rows


def precheck_text(rep: dict) -> str:
    """One line per checked VE: stable or not, spectral radius, K_max and margin; and what the
    device's Coulomb friction will do at the planned excitation, where the plan says
    (``labbench.analysis.friction.plan``)."""
    lines = []
    for c in rep.get("checks", []):
        ve = c["ve"]
        if ve.get("kind") == "none":
            lines.append("VE off (open loop): nothing is rendered, no stability bound to check")
            continue
        km = c.get("k_max")
        margin = (f", margin K_max/K = {km / ve['K']:.1f}x" if km and ve.get("K") else "")
        # K_max depends on the VE's damping: say which (commissioning's is for B = 0)
        at_b = f" at B = {fmt(ve['B'])} N s/m" if ve.get("B") is not None else ""
        bound = f"K_max = {km:.4g} N/m{at_b}" if km else "no K bound"
        lines.append(f"{'stable' if c['stable'] else 'UNSTABLE'} {ve['kind']}: spectral radius "
                     f"{c['spectral_radius']:.4f}; {bound}{margin}")
    friction = (rep.get("plan") or {}).get("friction")
    if friction:  # the stability probe, with the device's friction known
        kf, kl = friction.get("k_max"), friction.get("k_max_linear")
        where = (f"{kf:.4g} N/m ({kf / kl:.2g} x K_max) for its {1e3 * friction['swing_m']:.2g} mm "
                 "swing" if kf is not None and math.isfinite(kf) and kl else "beyond its cap")
        lines.append(f"with Coulomb friction {friction['coulomb_n']:.3g} N the probe expects the "
                     f"boundary at {where}")
    if isinstance(rep.get("friction"), dict):  # the ETFE's excitation against the device's friction
        lines.append(rep["friction"]["text"])
    return "pre-check: " + ("; ".join(lines) if lines else "nothing to check (open loop)")



def protocol_form(name: str, settings=None) -> SettingsForm:
    """The settings form of protocol ``name``: its defaults (``config.as_dict()``), then
    what ``settings`` (a QSettings, or None) remembers of it."""
    from dataclasses import fields

    from labbench.protocol import field_help
    from labbench.registry import make_protocol, protocol_class

    cls = protocol_class(name).Config
    config = make_protocol(name).config.as_dict()
    # a setting whose default is none but which validation filled in (a noise seed drawn at
    # random) is shown empty: else the drawn value was shown, saved, and every run repeated it
    drawn = frozenset(f.name for f in fields(cls) if f.default is None and config.get(f.name) is not None)
    config.update(dict.fromkeys(drawn))
    whole = frozenset(f.name for f in fields(cls) if f.default is None and "int" in str(f.type)
                      and "float" not in str(f.type))
    form = SettingsForm(config, helps=field_help(cls), whole=whole, drawn=drawn)
    if settings is not None:
        from labbench.gui.settings import load_protocol

        form.apply(load_protocol(settings, name))
    return form


def remember_form(settings, name: str, form: SettingsForm) -> None:
    """Keep what ``form`` shows as protocol ``name``'s settings (a half-typed number keeps
    what was remembered before)."""
    if settings is None:
        return
    from labbench.gui.settings import save_protocol

    try:
        save_protocol(settings, name, form.values())
    except UserError:
        pass


class ProtocolPanel(QtWidgets.QGroupBox):
    """The protocol the next Start runs, as the person chose it (nothing else changes the
    choice), its settings, the pre-check, Start / Stop and the run's progress. It owns its
    forms and what it remembers of them (``settings``: a QSettings, or None). The pre-check,
    Start, Stop and the progress are in ``run_box``, which the window places where it never
    scrolls away (at 1280 x 800 they scrolled out of view with the panels)."""

    start_requested = QtCore.Signal()
    stop_requested = QtCore.Signal()
    settings_changed = QtCore.Signal()
    protocol_changed = QtCore.Signal(str)

    def __init__(self, names, settings=None, parent=None):
        super().__init__("Protocol", parent)
        self.settings = settings
        self.choice = QtWidgets.QComboBox()
        self.choice.addItems(list(names))
        # one form per protocol, built once and kept: switching back shows the user's edits.
        # Plain Qt widgets, not pyqtgraph's ParameterTree: its items are Python subclasses of
        # QTreeWidgetItem (not QObjects), and PySide 6.11 crashed in releaseWrapper deleting
        # such an item whose wrapper it had already dropped, when a closed window was deleted
        self.forms = QtWidgets.QStackedWidget()
        self.forms.setMinimumHeight(150)  # about five settings; the window fits 1280 x 720
        # the room left over, whatever a form's own size: another protocol's longer form
        # scrolls in it instead of pushing Start down
        self.forms.setSizePolicy(QtWidgets.QSizePolicy.Policy.Preferred,
                                 QtWidgets.QSizePolicy.Policy.Ignored)
        self.built: dict[str, tuple[QtWidgets.QScrollArea, SettingsForm]] = {}
        self.form = SettingsForm({})
        self.forms.addWidget(self.form)
        self.precheck = QtWidgets.QLabel("pre-check: -")
        self.precheck.setWordWrap(True)
        self.precheck.setTextFormat(QtCore.Qt.TextFormat.RichText)
        self.precheck.setAlignment(QtCore.Qt.AlignmentFlag.AlignLeft | QtCore.Qt.AlignmentFlag.AlignTop)
        # the pre-check and the progress line in room of their own: a longer text scrolls
        # or wraps there, never pushes Start (below the pre-check) or anything else
        precheck_room = QtWidgets.QScrollArea()
        precheck_room.setWidgetResizable(True)
        precheck_room.setFrameShape(QtWidgets.QFrame.Shape.NoFrame)
        precheck_room.setWidget(self.precheck)
        precheck_room.setFixedHeight(5 * QtGui.QFontMetrics(self.precheck.font()).lineSpacing() + 6)
        self.start_button = QtWidgets.QPushButton("Start")
        self.stop_button = QtWidgets.QPushButton("Stop")
        self.stop_button.setEnabled(False)
        self.progress = QtWidgets.QProgressBar()
        self.progress.setRange(0, 1000)
        self.progress.setTextVisible(False)
        self.time_left = fixed_lines(QtWidgets.QLabel(""), 3)

        lay = QtWidgets.QVBoxLayout(self)
        lay.addWidget(self.choice)
        lay.addWidget(self.forms, 1)
        self.run_box = QtWidgets.QWidget()
        lay = QtWidgets.QVBoxLayout(self.run_box)
        lay.setContentsMargins(0, 0, 0, 0)
        lay.addWidget(precheck_room)
        row = QtWidgets.QHBoxLayout()
        row.addWidget(self.start_button)
        row.addWidget(self.stop_button)
        lay.addLayout(row)
        lay.addWidget(self.progress)
        lay.addWidget(self.time_left)

        self.choice.currentTextChanged.connect(self._show)
        self.start_button.clicked.connect(self.start_requested)
        self.stop_button.clicked.connect(self.stop_requested)
        remembered = settings.value("protocol/current", "", type=str) if settings else ""
        if remembered and self.choice.findText(remembered) >= 0:
            self.choice.setCurrentText(remembered)
        self._show(self.choice.currentText())

    @property
    def name(self) -> str:
        """The protocol chosen: what Start runs."""
        return self.choice.currentText()

    def _show(self, name: str) -> None:
        """Show the settings of protocol ``name``: its form as the user left it, or, the
        first time, one built from its defaults and what was remembered of it."""
        if name not in self.built:
            form = protocol_form(name, self.settings)
            form.changed.connect(self.settings_changed)
            scroll = QtWidgets.QScrollArea()
            scroll.setWidgetResizable(True)
            scroll.setWidget(form)
            self.forms.addWidget(scroll)
            self.built[name] = (scroll, form)
        page, self.form = self.built[name]
        self.forms.setCurrentWidget(page)
        self.protocol_changed.emit(name)

    def values(self) -> dict:
        return self.form.values()

    def state(self) -> dict:
        """What the form shows, field by field (goes into the run's start record)."""
        return self.form.shown()

    def set_value(self, name: str, value) -> None:
        self.form.fields[name].set(value)

    def save_state(self) -> None:
        """Remember the protocol chosen and the settings of every protocol shown."""
        if self.settings is None:
            return
        self.settings.setValue("protocol/current", self.name)
        for name, (_page, form) in self.built.items():
            remember_form(self.settings, name, form)

    def set_precheck(self, text: str, ok: bool | None, tip: str = "") -> None:
        """``ok``: green (True), red (False) or grey (None: not yet the run's own check)."""
        colour = {True: "#206020", False: "#b00020", None: "#555555"}[ok]
        self.precheck.setText(f'<span style="color:{colour}">{escape(text, quote=False)}</span>')
        self.precheck.setToolTip(tip)

    def follow(self, state) -> None:
        """The run's state (``RunState``): Start while one may start, Stop while a run or
        replay goes on (once), the choice and the form fixed during a run."""
        from labbench.gui.run_state import RUNNING

        self.start_button.setEnabled(state.can_start)
        self.start_button.setToolTip(state.why_not_start())
        self.stop_button.setEnabled(state.can_stop)
        fixed = state.activity == RUNNING
        self.choice.setEnabled(not fixed)
        self.forms.setEnabled(not fixed)

    def set_progress(self, frac: float, text: str = "") -> None:
        self.progress.setValue(int(1000 * min(max(frac, 0.0), 1.0)))
        set_text(self.time_left, text)
