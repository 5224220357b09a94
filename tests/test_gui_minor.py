"""Issue 43, the minor defects a stranger's walkthrough left (43E): each clicked through or
drawn offscreen as a person meets it, asserting what the screen then shows. Each test failed
before its fix."""
import os

os.environ["QT_QPA_PLATFORM"] = "offscreen"  # before any Qt import

import pytest  # noqa: E402
from PySide6 import QtCore, QtWidgets  # noqa: E402

from test_gui_holds import window  # noqa: E402,F401 (a fixture)


def form_label(panel, name: str) -> str:
    layout = panel.form.layout()
    return layout.labelForField(panel.form.fields[name].widget).text()


def test_the_coulomb_interval_field_reads_as_words_and_takes_its_two_numbers(qtbot, window):
    """The ETFE form showed the raw name "plant coulomb ci95 (opt.)" and took one number only,
    so the interval it asks for could not be typed. Now it reads as words with its unit and
    takes "lo, hi", which the protocol accepts."""
    from labbench.registry import make_protocol

    panel = window().protocol_panel
    panel.choice.setCurrentText("etfe")
    label = form_label(panel, "plant_coulomb_ci95")
    assert "ci95" not in label and "95 % interval" in label and "[N]" in label, label
    assert "[N]" in form_label(panel, "plant_coulomb_n")
    fields = panel.form.fields
    fields["plant_coulomb_n"].widget.setText("0.02")
    fields["plant_coulomb_ci95"].widget.setText("0.019, 0.021")
    values = panel.form.values()
    assert values["plant_coulomb_ci95"] == [0.019, 0.021]
    cfg = make_protocol("etfe", **values).config
    assert tuple(cfg.plant_coulomb_ci95) == (0.019, 0.021)
    fields["plant_coulomb_ci95"].widget.setText("0.019")  # one number is not an interval
    assert "#b00020" in fields["plant_coulomb_ci95"].widget.styleSheet()


def test_a_stability_probe_s_progress_line_says_k_to_four_digits(qtbot, window):
    """The probe's progress line read "K=51.8748: 40 %" (its step's name, recorded in the
    session to six digits). Now the line says "K = 51.87 N/m" while the session keeps the
    six-digit step names that its readers match."""
    import re

    from labbench.sessions.session_content import load_session
    from test_gui_holds import run_protocol

    win = window()
    shown = []
    set_progress = win.protocol_panel.set_progress
    win.protocol_panel.set_progress = lambda frac, text="": (shown.append(text),
                                                             set_progress(frac, text))
    path = run_protocol(qtbot, win, "stability")
    steps = [t for t in shown if "K" in t]
    assert steps, shown
    for text in steps:
        found = re.search(r"K = ([0-9.]+) N/m", text)
        assert found and len(found.group(1).replace(".", "").lstrip("0")) <= 4, text
    segments = [e for e in load_session(path)[3] if e.get("name") == "segment"]
    probed = [(e["reason"], e["ve"]["K"]) for e in segments if e.get("role") == "probe"]
    assert probed and all(label.endswith(f"K={K:.6g}") for label, K in probed), probed


def test_the_sessions_table_shows_a_probe_s_boundary_and_its_agreement(qtbot, window):
    """The Sessions table left a stability probe's verdict column empty and its K column said
    only where it started ("from 20"). Now the K column holds the measured K_max and the
    verdict column its agreement, as the readout words them."""
    from labbench.gui.sessions_view import COLUMNS
    from labbench.readout.wording import of_results
    from test_gui_holds import run_protocol

    win = window()
    path = run_protocol(qtbot, win, "stability")
    win.tabs.setCurrentWidget(win.sessions)
    win.refresh_sessions()
    name = path.rsplit("/", 1)[-1]
    qtbot.waitUntil(lambda: bool(win.sessions.table.findItems(name, QtCore.Qt.MatchFlag.MatchExactly)),
                    timeout=10_000)
    r = win.sessions.table.findItems(name, QtCore.Qt.MatchFlag.MatchExactly)[0].row()
    row = {c: win.sessions.table.item(r, j).text() for j, c in enumerate(COLUMNS)}
    rows = dict(of_results("stability", win.last_run.results).row_texts())
    measured = rows["boundary (K), measured"].split(" ")[0]  # '200.0355 N/m (...)'
    assert row["K [N/m]"] == f"K_max {measured} (from 20)", row
    assert row["verdict"] == f"against exact: {rows['measured against exact']}", row


def test_the_sweeps_page_gives_the_boundary_its_unit_and_its_status_line_room(qtbot, window, tmp_path):
    """On the Sweeps page a stability map's y axis read "measured boundary" with no unit, and
    the status line beside the progress bar was cut ("stopped: the 4 points asked f"). Now
    the axis says N/m (s for a td probe) and the line has a row of its own, whole."""
    from PySide6 import QtGui

    from labbench.gui.sweep_runner import limit_reached
    from labbench.sweep import table as tables

    folder = tmp_path / "map.sweep"
    folder.mkdir()
    writer = tables.TableWriter(folder)
    for i, (td, k) in enumerate(((0.0, 200.04), (0.001, 124.7), (0.002, 90.1))):
        writer.append({"key": f"k{i}", "index": i, "status": "ok", "td_s": td,
                       "res.variable": "K", "res.measured_boundary": k})
    writer.close()
    win = window()  # 1280 x 800
    view = win.sweeps
    win.tabs.setCurrentWidget(view)
    assert view.open_table(folder)
    view.x.setCurrentIndex(view.x.findData("td_s"))
    view.y.setCurrentIndex(view.y.findData("res.measured_boundary"))
    left = view.plot.getPlotItem().getAxis("left").labelText
    assert left == "measured boundary [N/m]", left
    assert view.y.currentText() == "measured boundary [N/m]"

    text = f"4 of 36 points, 0 not ok, stopped: {limit_reached(4)}"
    view._show_progress(4, 36, text.split(", ", 1)[1])
    QtWidgets.QApplication.processEvents()
    label = view.progress_text
    room = label.contentsRect()
    need = QtGui.QFontMetrics(label.font()).boundingRect(
        QtCore.QRect(0, 0, room.width(), 10_000), QtCore.Qt.TextFlag.TextWordWrap, label.text())
    assert label.text() == text and need.height() <= room.height() and need.width() <= room.width(), \
        (need, room)
    assert win.width() <= 1280 and label.mapTo(win, QtCore.QPoint(room.right(), 0)).x() < win.width()


def test_the_force_legend_leaves_the_traces_whole(qtbot, window):
    """The force plot's legend box (excitation, command) lay over the traces' right end, the
    newest samples. Now it sits outside the plot's data area, both names still shown."""
    from test_gui_holds import run_protocol

    win = window()
    run_protocol(qtbot, win, "etfe", duration_s=1.0, seed=1)
    traces = win.live.traces
    QtWidgets.QApplication.processEvents()
    import pyqtgraph as pg

    legend, = [item for item in traces.scene().items() if isinstance(item, pg.LegendItem)]
    box = legend.mapRectToScene(legend.boundingRect())
    data = traces.plots["force"].getViewBox()
    area = data.mapRectToScene(data.boundingRect())
    assert legend.isVisible() and box.width() > 0 and not box.intersects(area), (box, area)
    names = [label.text for _sample, label in legend.items]
    assert names == ["excitation", "command"]
    assert box.bottom() <= traces.sceneRect().bottom() + 1  # inside the widget, not cut


def test_the_design_page_follows_the_display_units(qtbot, window):
    """Under Hz the Design page still wrote w0, w_s* and w_b* in rad/s and drew the ED plot
    over rad/s (each number with its unit, but not the unit chosen). Now all four follow the
    units chosen in the window's corner, to the same values."""
    import math

    win = window()
    design = win.design
    win.tabs.setCurrentWidget(design)
    p = design.point
    ws, wb, w0 = p.ws_star, p.wb_star, design.value("w0")
    assert design.values["w0"].text().endswith("rad/s")
    win.units_choice.combos["frequency"].setCurrentText("Hz")  # as a person picks it
    cells = design.numbers.cells
    hz = 1 / (2 * math.pi)
    for text, w in ((cells["ws_star"].text(), ws), (cells["wb_star"].text(), wb),
                    (design.values["w0"].text(), w0)):
        value, unit = text.split(" ")
        assert unit == "Hz" and float(value) == pytest.approx(w * hz, rel=1e-3), text
    axis = design.ed_plot.getAxis("bottom").labelText
    assert "Hz" in axis and "rad/s" not in axis, axis
    x = design.curves["ed_sampled"].xData  # as given (getData is log10 on a log axis)
    T = design.value("T")
    assert x[-1] == pytest.approx(0.3 * math.pi / T * hz, rel=1e-9)  # W_MAX_NYQUIST
    assert 10 ** design.wb_line.value() == pytest.approx(wb * hz, rel=1e-9)


def test_the_left_column_grows_when_the_window_is_maximised(qtbot, window):
    """Opened at 1600 x 1000 and maximised on a 1920 x 1080 screen, the left column (device,
    settings, pre-check) stayed 440 px while the pages took all the new room. Now it follows
    the window's width (440 + 30 % of the width over 1600, at most 560) until the person
    drags the divider; then their width stands."""
    win = window(size=(1600, 1000))
    assert win.body.sizes()[0] == 440
    win.resize(1920, 1080)  # what maximising on that screen does
    qtbot.waitUntil(lambda: win.width() == 1920)
    assert win.body.sizes()[0] == 536, win.body.sizes()  # 440 + 0.3 * 320
    from PySide6.QtTest import QTest

    handle = win.body.handle(1)  # the person drags the divider 56 px left
    middle = handle.rect().center()
    QTest.mousePress(handle, QtCore.Qt.MouseButton.LeftButton, pos=middle)
    QTest.mouseMove(handle, middle - QtCore.QPoint(56, 0))
    QTest.mouseRelease(handle, QtCore.Qt.MouseButton.LeftButton, pos=middle - QtCore.QPoint(56, 0))
    assert win.body.sizes()[0] == 480, win.body.sizes()
    win.resize(1700, 1000)
    qtbot.waitUntil(lambda: win.width() == 1700)
    assert win.body.sizes()[0] == 480, win.body.sizes()
