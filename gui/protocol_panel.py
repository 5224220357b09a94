"""Protocol panel: choice of protocol, its settings in a ParameterTree, pre-check, Start/Stop, progress.

The tree is built from the protocol's own validated config (``config.as_dict()``
of ``labbench.protocols.make_protocol(name)``), so new settings appear without GUI
changes; units and limits come from the name suffix convention of the project
(``_s``, ``_hz``, ``_n``, ``_m``...) and from the VE's fields. The protocol
validates the values itself when Start is pressed.
"""
from __future__ import annotations

import math
from html import escape

from pyqtgraph.parametertree import Parameter, ParameterTree
from PySide6 import QtCore, QtWidgets

from labbench.errors import UserError
from labbench.ve import VE_KINDS

# name or suffix -> (unit, lower limit); the protocol itself enforces the real bounds
UNITS = {
    "K": ("N/m", 0.0), "B": ("N s/m", 0.0), "w0": ("rad/s", 1e-3), "T": ("s", 1e-6), "td": ("s", 0.0),
    "m": ("kg", 1e-6), "b": ("N s/m", 0.0), "plant_b": ("N s/m", 0.0), "_kg": ("kg", 0.0),
    "_s": ("s", 0.0), "_hz": ("Hz", 0.0), "_n": ("N", 0.0), "_m": ("m", 0.0), "_j": ("J", 0.0),
    "_rad_s": ("rad/s", 0.0), "_n_per_s": ("N/s", 0.0), "_m_s": ("m/s", 0.0),
}
def choices() -> dict[str, list[str]]:
    """Text fields with a fixed set of values: shown as drop-down lists."""
    from labbench.analysis.identify import MODEL_CHOICES
    from labbench.protocols.excitation import SWEEPS
    from labbench.protocols.stability_probe import PROBE_KINDS, VARIABLES

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
        return (*UNITS[name], name.replace("_", " "))
    for suffix in sorted((k for k in UNITS if k.startswith("_")), key=len, reverse=True):
        if name.endswith(suffix):
            return (*UNITS[suffix], name[: -len(suffix)].replace("_", " "))
    return ("", None, name.replace("_", " "))


def params_from_config(config: dict, choice_lists: dict | None = None) -> list[dict]:
    """ParameterTree children for a (nested) config dict of numbers, bools, strings and lists."""
    lists = choices() if choice_lists is None else choice_lists
    children = []
    for name, value in config.items():
        unit, low, label = _unit(name)
        item = {"name": name, "title": f"{label} [{unit}]" if unit else label, "tip": name}
        if isinstance(value, dict):
            item.update(type="group", children=params_from_config(value, lists))
        elif isinstance(value, bool):
            item.update(type="bool", value=value)
        elif isinstance(value, int):
            # 64-bit limits: a 32-bit limit showed a seed drawn above 2^31 as 2147483648
            item.update(type="int", value=value, limits=(int(low) if low is not None else -2**63,
                                                         2**63 - 1))
        elif isinstance(value, float):
            item.update(type="float", value=value, dec=True, step=1.0, minStep=1e-9,
                        limits=(low if low is not None else -math.inf, math.inf))
        elif name in lists and (value is None or isinstance(value, str)):
            # "" stands for None: the protocol's default
            options = {v: v for v in lists[name]}
            if value is None:
                options = {"(default)": "", **options}
            item.update(type="list", limits=options, value="" if value is None else value,
                        optional_choice=value is None)
        elif value is None:  # optional number: empty text = the protocol's default / none
            item.update(type="str", value="", optional_number=True,
                        tip="empty: not set (default, or no filter for w0)")
            item["title"] += " (opt.)"
        elif isinstance(value, str):
            item.update(type="str", value=value)
        elif isinstance(value, (list, tuple)) and all(isinstance(v, (int, float)) for v in value):
            item.update(type="str", value=", ".join(f"{v:g}" for v in value), list_of_numbers=True)
        else:
            continue  # not editable here (the protocol keeps its default)
        children.append(item)
    return children


def settings_rows(config: dict, prefix: str = "") -> list[tuple[str, str]]:
    """(label with unit, value) per setting of a (nested) config, for a table a person reads
    (the run's start in the event log); a None is the protocol's default."""
    from labbench.numfmt import fmt

    rows = []
    for name, value in config.items():
        unit, _low, label = _unit(name)
        if isinstance(value, dict):
            rows += settings_rows(value, f"{prefix}{label}: ")
            continue
        text = "default" if value is None else fmt(value, 6)
        rows.append((f"{prefix}{label}", f"{text} {unit}" if unit and value is not None else text))
    return rows


def values_of(param: Parameter) -> dict:
    """Nested plain values of a tree built by ``params_from_config`` (lists parsed back)."""
    out = {}
    for child in param.children():
        if child.type() == "group":
            out[child.name()] = values_of(child)
        elif child.opts.get("list_of_numbers"):
            out[child.name()] = [_number(child.name(), v) for v in str(child.value()).split(",")
                                 if v.strip()]
        elif child.opts.get("optional_choice"):
            out[child.name()] = child.value() or None
        elif child.opts.get("optional_number"):
            text = str(child.value()).strip()
            out[child.name()] = _number(child.name(), text) if text else None
        else:
            out[child.name()] = child.value()
    return out


def _number(name: str, text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise UserError(f"{name}: {text!r} is not a number") from None


class ProtocolPanel(QtWidgets.QGroupBox):
    start_requested = QtCore.Signal()
    stop_requested = QtCore.Signal()
    settings_changed = QtCore.Signal()
    protocol_changed = QtCore.Signal(str)

    def __init__(self, names, parent=None):
        super().__init__("Protocol", parent)
        self.choice = QtWidgets.QComboBox()
        self.choice.addItems(list(names))
        # one tree per protocol, built once and never cleared: clearing a ParameterTree
        # deletes its QTreeWidgetItems in C++ while PySide still maps their addresses to the
        # Python wrappers until a GC pass frees them, and a QMenu made at such an address
        # came back as a QTreeWidgetItem (pyqtgraph's PlotItem then failed, and the process
        # crashed at exit), seen after many protocol switches on a loaded machine
        self.trees = QtWidgets.QStackedWidget()
        self.trees.setMinimumHeight(220)
        self.built: dict[str, tuple[ParameterTree, Parameter]] = {}
        self.tree = ParameterTree(showHeader=False)
        self.params = Parameter.create(name="settings", type="group", children=[])
        self.tree.setParameters(self.params, showTop=False)
        self.trees.addWidget(self.tree)
        self.precheck = QtWidgets.QLabel("pre-check: -")
        self.precheck.setWordWrap(True)
        self.precheck.setTextFormat(QtCore.Qt.TextFormat.RichText)
        self.start_button = QtWidgets.QPushButton("Start")
        self.stop_button = QtWidgets.QPushButton("Stop")
        self.stop_button.setEnabled(False)
        self.progress = QtWidgets.QProgressBar()
        self.progress.setRange(0, 1000)
        self.progress.setTextVisible(False)
        self.time_left = QtWidgets.QLabel("")

        lay = QtWidgets.QVBoxLayout(self)
        lay.addWidget(self.choice)
        lay.addWidget(self.trees, 1)
        lay.addWidget(self.precheck)
        row = QtWidgets.QHBoxLayout()
        row.addWidget(self.start_button)
        row.addWidget(self.stop_button)
        lay.addLayout(row)
        lay.addWidget(self.progress)
        lay.addWidget(self.time_left)

        self.choice.currentTextChanged.connect(self.protocol_changed)
        self.start_button.clicked.connect(self.start_requested)
        self.stop_button.clicked.connect(self.stop_requested)

    def show_protocol(self, name: str, config: dict) -> bool:
        """Show the settings of protocol ``name``: its tree as the user left it, or, the first
        time, one built from its default ``config`` (returns True then)."""
        new = name not in self.built
        if new:
            params = Parameter.create(name="settings", type="group", children=params_from_config(config))
            tree = ParameterTree(showHeader=False)
            tree.setParameters(params, showTop=False)
            params.sigTreeStateChanged.connect(lambda *a: self.settings_changed.emit())
            self.trees.addWidget(tree)
            self.built[name] = (tree, params)
        self.tree, self.params = self.built[name]
        self.trees.setCurrentWidget(self.tree)
        return new

    def values(self) -> dict:
        return values_of(self.params)

    def state(self) -> dict:
        """The tree's ``saveState()`` (goes into the run's start record)."""
        return self.params.saveState(filter="user")

    def set_value(self, path: tuple[str, ...], value) -> None:
        self.params.child(*path).setValue(value)

    def apply_values(self, values: dict, parent: Parameter | None = None) -> None:
        """Put remembered ``values`` (as ``values()`` gave them) back into the tree; names
        the protocol no longer has, and values a field refuses, are left out."""
        parent = self.params if parent is None else parent
        for child in parent.children():
            if child.name() not in values:
                continue
            value = values[child.name()]
            if child.type() == "group":
                if isinstance(value, dict):
                    self.apply_values(value, child)
                continue
            if child.opts.get("list_of_numbers") and isinstance(value, list):
                value = ", ".join(f"{v:g}" for v in value)
            elif child.opts.get("optional_choice") or child.opts.get("optional_number"):
                value = "" if value is None else (value if isinstance(value, str) else f"{value:g}")
            try:
                child.setValue(value)
            except (TypeError, ValueError):
                continue  # a value of another type than the field now has

    def set_precheck(self, text: str, ok: bool | None) -> None:
        colour = {True: "#206020", False: "#b00020", None: "#555555"}[ok]
        self.precheck.setText(f'<span style="color:{colour}">{escape(text, quote=False)}</span>')

    def set_running(self, running: bool) -> None:
        self.start_button.setEnabled(not running)
        self.stop_button.setEnabled(running)
        self.choice.setEnabled(not running)
        self.trees.setEnabled(not running)

    def set_progress(self, frac: float, text: str = "") -> None:
        self.progress.setValue(int(1000 * min(max(frac, 0.0), 1.0)))
        self.time_left.setText(text)
