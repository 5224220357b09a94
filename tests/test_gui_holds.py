"""Issue 43, "the window says only what holds": each defect a stranger found, clicked through
as a person does (synthesised wheel, keys and clicks, offscreen), asserting what the screen
then says. Each test failed before its fix."""
import os

os.environ["QT_QPA_PLATFORM"] = "offscreen"  # before any Qt import

import pytest  # noqa: E402
from PySide6 import QtCore, QtGui, QtWidgets  # noqa: E402

from labbench.gui.main_window import MainWindow  # noqa: E402
from labbench.gui.wheel_guard import takes_wheel  # noqa: E402
from labbench.rig import Rig  # noqa: E402


@pytest.fixture
def window(qtbot, tmp_path):
    def make(rig=None, size=(1280, 800), **kw):
        win = MainWindow(rig or Rig(), tmp_path / "sessions", realtime=False, **kw)
        qtbot.addWidget(win)
        win.resize(*size)
        win.show()
        qtbot.waitExposed(win)
        return win

    return make


def wheel(widget, steps: int) -> None:
    """``steps`` notches of the mouse wheel over the middle of ``widget`` (+: away from the
    person, i.e. up), as the platform delivers them."""
    pos = QtCore.QPointF(widget.width() / 2, widget.height() / 2)
    glob = QtCore.QPointF(widget.mapToGlobal(pos.toPoint()))
    for _ in range(abs(steps)):
        ev = QtGui.QWheelEvent(pos, glob, QtCore.QPoint(0, 0), QtCore.QPoint(0, 120 if steps > 0 else -120),
                               QtCore.Qt.MouseButton.NoButton, QtCore.Qt.KeyboardModifier.NoModifier,
                               QtCore.Qt.ScrollPhase.NoScrollPhase, False)
        QtWidgets.QApplication.sendEvent(widget, ev)


def value_of(w):
    if isinstance(w, QtWidgets.QComboBox):
        return w.currentIndex(), w.currentText()
    return w.value()


def every_setting(win) -> list:
    """Every widget of the window whose value a wheel could change, with every protocol's
    form built (each protocol shown once)."""
    panel = win.protocol_panel
    for i in range(panel.choice.count()):
        panel.choice.setCurrentIndex(i)
    panel.choice.setCurrentIndex(0)
    return [w for w in win.findChildren(QtWidgets.QWidget) if takes_wheel(w)]


def test_the_wheel_never_changes_a_setting_it_passes_over(qtbot, window):
    """The estimator went h1-log -> (default) -> lpm under a wheel that meant to scroll the
    Protocol box; now no drop-down, spin box or slider without the focus takes the wheel."""
    win = window()
    widgets = every_setting(win)
    combos = [w for w in widgets if isinstance(w, QtWidgets.QComboBox)]
    assert len(combos) >= 10  # protocols, every form's lists, backend, units, overlay plant, ...
    win.setFocus()
    for w in widgets:
        assert w.focusPolicy() != QtCore.Qt.FocusPolicy.WheelFocus, w  # the wheel gives no focus
        before = value_of(w)
        wheel(w, -3)
        wheel(w, +5)
        assert value_of(w) == before, (type(w).__name__, w.toolTip())
        assert not w.hasFocus()

    # the estimator of the etfe form, as in the report; the wheel scrolls its form instead
    panel = win.protocol_panel
    panel.choice.setCurrentText("etfe")
    estimator = panel.form.fields["estimator"].widget
    scroll = panel.built["etfe"][0]
    win.resize(1280, 700)  # short enough that the form scrolls
    qtbot.waitUntil(lambda: scroll.verticalScrollBar().maximum() > 0)
    scroll.verticalScrollBar().setValue(0)
    shown = estimator.currentText()
    wheel(estimator, -2)
    assert estimator.currentText() == shown
    assert scroll.verticalScrollBar().value() > 0  # the panel moved, not the value

    # a list the person clicked into (it has the focus) takes the wheel as Qt's always did
    estimator.setFocus()
    qtbot.waitUntil(estimator.hasFocus)
    wheel(estimator, -1)
    assert estimator.currentText() != shown
