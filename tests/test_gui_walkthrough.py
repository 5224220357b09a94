"""Issue 43, a stranger's walkthrough (43C): what a newcomer met in the window under Xvfb at
1280 x 800, each clicked through as a person does (offscreen), asserting what the screen
then shows. Each test failed before its fix."""
import os

os.environ["QT_QPA_PLATFORM"] = "offscreen"  # before any Qt import

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from PySide6 import QtCore, QtGui, QtWidgets  # noqa: E402


from test_gui_holds import plain, run_protocol, window  # noqa: E402,F401 (window: a fixture)


def test_the_first_window_fits_the_screen(qtbot, window, monkeypatch):
    """On a 1280 x 800 screen the window opened 1600 x 1000: Start, Stop, the pre-check, the
    log and half the plots lay off the screen. Now its first size is the screen's room."""
    monkeypatch.setattr(QtGui.QScreen, "availableGeometry", lambda self: QtCore.QRect(0, 0, 1280, 800))
    win = window(size=None)  # as `labbench gui` opens it the first time (nothing remembered)
    assert win.width() <= 1280 and win.height() <= 800, (win.width(), win.height())
    start = win.protocol_panel.start_button
    corner = start.mapTo(win, QtCore.QPoint(start.width(), start.height()))
    assert corner.x() <= 1280 and corner.y() <= 800


def test_a_start_on_another_page_shows_the_run(qtbot, window):
    """After a chirp-ID the window showed the Identification page; Start of an ETFE there
    (or on the Sessions page) ran unseen: its traces and, at its end, the rendered K and B
    and the verdicts are on the Live page. Now a Start shows the Live page."""
    win = window()
    win.tabs.setCurrentWidget(win.sessions)
    run_protocol(qtbot, win, "etfe", duration_s=2.0, seed=1)
    assert win.tabs.currentWidget() is win.live
    assert plain(win.live.verdicts)[0].startswith("etfe, ")  # its result, where it shows


def test_a_stability_probe_says_its_boundary_and_no_effective_impedance(qtbot, window):
    """A stability probe's Live page drew one ETFE over all its steps (K 20 -> 200, limit
    cycles) against the first step's theory and marked "w_s* = 14.13 rad/s (sampled theory
    14.58)" as measured; its result, the boundary, was in the log alone (the verdicts' room
    said the verdicts show there once it ends). Now the plots say why they are empty and
    the boundary heads the page, as the report's page 1 has it."""
    win = window()
    run_protocol(qtbot, win, "stability")
    lines = plain(win.live.verdicts)
    assert lines[0].startswith("stability, "), lines
    measured = win.last_run.results["measured_boundary"]
    head, shown = lines[1].split(": ", 1)
    assert head == "boundary (K), measured" and shown.endswith(")"), lines  # with its interval
    assert float(shown.split(" N/m")[0]) == pytest.approx(measured, rel=1e-6)
    exact = next(x for x in lines if x.startswith("boundary (K), exact sampled: ")).split(": ")[1]
    assert float(exact.split(" N/m")[0]) == pytest.approx(win.last_run.results["exact_boundary"], rel=1e-5)
    imp = win.live.impedance  # the final estimate would come with the run's end
    qtbot.waitUntil(lambda: "stability probe" in imp.title.text, timeout=10_000)
    assert not any(m.isVisible() for m in imp.marks.values()) and not imp.legend.isVisible()
    assert all(c.getOriginalDataset()[0].size == 0 for c in imp.curves.values())


def test_the_marks_labels_never_hide_the_measured_curve(qtbot, window):
    """The w_s* and w_b* labels sat on a white ground left of their marks (pyqtgraph chose
    the side by the view's vertical centre), over the measured ES and ED in the band K and B
    are read from: the curves looked faint exactly there. Now a label on a ground lies
    right of its mark, where the curve it marks has ended or falls away; with no room there
    it goes left with no ground."""
    win = window()
    run_protocol(qtbot, win, "etfe", K=50.0, B=1.0, duration_s=20.0, seed=3)
    imp = win.live.impedance
    qtbot.waitUntil(lambda: imp.last is not None and imp.last.estimator != "live-welch"
                    and imp.marks["wb"].isVisible(), timeout=30_000)
    QtWidgets.QApplication.processEvents()
    est = imp.last
    fx = imp.units.frequency_of(1.0)
    checked = 0
    for key, plot, y in (("ws", "ES", np.where(est.Z.imag < 0, est.ES, np.nan)), ("wb", "ED", est.ED)):
        mark = imp.marks[key]
        assert mark.isVisible()
        if mark.label.fill.style() == QtCore.Qt.BrushStyle.NoBrush:
            continue  # no ground: the curve shows through
        vb = imp.plots[plot].getViewBox()
        box = mark.label.sceneBoundingRect()
        below = (est.w > 0) & (np.log10(est.w * fx) < mark.value()) & np.isfinite(y)
        hidden = [w for w, v in zip(est.w[below], y[below])
                  if box.contains(vb.mapViewToScene(QtCore.QPointF(np.log10(w * fx), v)))]
        assert not hidden, f"{key}: {len(hidden)} measured points under the label, from {hidden[0]:.3g} rad/s"
        checked += 1
    assert checked >= 1  # at 1280 x 800 the w_s* label has room right of its mark


def test_an_exported_path_does_not_widen_the_window(qtbot, window):
    """After Export report the Sessions page's line held the written files' paths, and the
    window grew from 1280 to 1922 px, past the screen: the units, Refresh and Cancel off
    it, the left column squeezed. Now the line wraps and cuts, the paths whole in its
    tooltip."""
    win = window()
    path = run_protocol(qtbot, win, "chirp-id", f0_hz=0.5, duration_s=2.0)
    win.tabs.setCurrentWidget(win.sessions)
    qtbot.waitUntil(lambda: path in win.sessions.paths, timeout=20_000)
    win.sessions.select_path(path)
    win.sessions.buttons["Export CSV"].click()
    qtbot.waitUntil(lambda: win.sessions.progress_line.text().startswith("exported: "), timeout=60_000)
    QtWidgets.QApplication.processEvents()
    assert win.width() <= 1280 and win.minimumSizeHint().width() <= 1280, win.width()
    assert ".csv" in win.sessions.progress_line.toolTip()


def test_a_log_axis_writes_its_decades_alike(qtbot):
    """After a switch to Hz the impedance axes read '0.1, 1, 10\u00b9, 10\u00b2' (pyqtgraph's
    notation changes at 10); now one notation per axis."""
    from labbench.gui.live_plots import DecadeAxis

    axis = DecadeAxis("bottom")
    assert axis.logTickStrings([-1.0, -0.5, 0.0, 1.0, 2.0, 3.0], 1.0, 1.0) == ["0.1", "", "1", "10", "100", "1000"]
