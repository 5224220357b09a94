"""The Sweeps tab, driven: a real small sweep table opened, axes picked, the plotted points
against the table, the row of the point under the mouse, a kept session opened and a point
re-run as a session (in the view and through the main window)."""
import os

os.environ["QT_QPA_PLATFORM"] = "offscreen"  # before any Qt import

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from PySide6 import QtCore  # noqa: E402

from labbench.gui.main_window import MainWindow  # noqa: E402
from labbench.gui.sweep_view import SweepView  # noqa: E402
from labbench.readout.numfmt import fmt  # noqa: E402
from labbench.rig import Rig  # noqa: E402
from labbench.sessions.session_content import load_session  # noqa: E402
from labbench.sessions.session_format import looks_like_session  # noqa: E402
from labbench.sweep import table as tables  # noqa: E402
from labbench.sweep.engine import run_sweep  # noqa: E402
from labbench.sweep.spec import spec_from_dict  # noqa: E402

RUN_TIMEOUT_MS = 120_000
# six 2 s ETFE runs; K = 5000 N/m is beyond K_max (1212 N/m): refused, a row without results
SPEC = {"sweep": {"name": "gui", "protocol": "etfe"}, "fixed": {"duration_s": 2.0},
        "grid": {"K": [20.0, 50.0, 5000.0], "seed": [1, 2]},
        "chart": [{"kind": "map", "x": "K", "y": "truth.k_max", "color": "seed", "log_x": False}]}


@pytest.fixture(scope="module")
def small_table(tmp_path_factory):
    d = tmp_path_factory.mktemp("gui-sweep")
    kept = d / "kept"
    kept.mkdir()
    s = run_sweep(spec_from_dict(SPEC), d / "t.sweep", workers=0, keep_sessions=kept)
    rows = tables.read_table(s.table).to_pylist()
    assert len(rows) == 6 and sum(r["status"] == "refused" for r in rows) == 2
    return s.table, rows


@pytest.fixture
def view(qtbot, tmp_path):
    v = SweepView(tmp_path / "sessions")
    qtbot.addWidget(v)
    v.resize(1200, 700)
    v.show()
    return v


def pick(view, x, y, color="(none)", log_x=False, log_y=False):
    """Choose the columns named (the lists show their labels, with units)."""
    for combo, name in ((view.x, x), (view.y, y), (view.color, color)):
        combo.setCurrentIndex(combo.findData(name))
    view.log_x.setChecked(log_x)
    view.log_y.setChecked(log_y)


def plotted(view) -> dict[int, tuple[float, float, str]]:
    """Table row -> (x, y, symbol) of every spot drawn."""
    d = view.points.data
    return {int(r): (x, y, s) for r, x, y, s in zip(d["data"], d["x"], d["y"], d["symbol"])}


def spot_pos(qtbot, view, row: int) -> QtCore.QPoint:
    """Where the spot of table row ``row`` is, in the plot's viewport pixels."""
    vb = view.plot.getPlotItem().getViewBox()
    spot = next(p for p in view.points.points() if p.data() == row)
    # the view range follows new data at the next paint, and its padding the laid-out size:
    # the place is where it stays over two paints
    places = []

    def settled():
        if vb.width() > 100 and vb.viewRect().contains(spot.pos()):
            places.append(view.plot.mapFromScene(vb.mapViewToScene(spot.pos())))
        qtbot.wait(40)
        return len(places) >= 2 and places[-1] == places[-2]

    qtbot.waitUntil(settled)
    return places[-1]


def shown_row(view) -> dict[str, str]:
    t = view.row_view
    return {t.item(i, 0).text(): t.item(i, 1).text() for i in range(t.rowCount())}


def test_picked_axes_plot_the_tables_values(view, small_table):
    folder, rows = small_table
    assert view.open_table(folder)
    assert "6 rows" in view.table_label.text()
    # first shown as the spec's chart draws it (K spans 250x, but the chart says linear)
    assert (view.x.currentData(), view.y.currentData(), view.color.currentData()) == \
        ("K", "truth.k_max", "seed")
    assert view.x.currentText() == "K [N/m]" and view.y.currentText() == "truth: K_max [N/m]"
    assert not view.log_x.isChecked() and not view.log_y.isChecked()
    # K spans 250x: its axis starts as log; the refused rows have no truth.median_rel
    pick(view, "K", "truth.median_rel")
    view.log_x.setChecked(True)
    want = {i: (np.log10(r["K"]), r["truth.median_rel"], "o")
            for i, r in enumerate(rows) if r["status"] == "ok"}
    assert plotted(view).keys() == want.keys()
    for i, (x, y, symbol) in plotted(view).items():
        assert (x, y) == pytest.approx(want[i][:2], rel=1e-12) and symbol == "o"
    assert "2 rows without a value to plot" in view.legend.text()
    # linear axes, both parameters: every row, the refused ones as crosses
    pick(view, "K", "seed", color="status")
    got = plotted(view)
    assert got == {i: (r["K"], r["seed"], "o" if r["status"] == "ok" else "x")
                   for i, r in enumerate(rows)}
    assert "ok" in view.legend.text() and "refused" in view.legend.text()
    # a log axis leaves out what it cannot show
    pick(view, "truth.median_rel", "K", log_x=True)
    assert set(plotted(view)) == {i for i, r in enumerate(rows) if r["status"] == "ok"}


def test_hovering_a_point_shows_its_row(qtbot, view, small_table):
    folder, rows = small_table
    view.open_table(folder)
    pick(view, "K", "seed", color="truth.median_rel")
    for i in (3, 4):  # an ok row and a refused one
        qtbot.mouseMove(view.plot.viewport(), spot_pos(qtbot, view, i))
        qtbot.waitUntil(lambda: view.hovered == i)
        assert shown_row(view) == {k: fmt(v, 6) for k, v in rows[i].items()}
        assert view.row_title.text() == f"point {rows[i]['index']} (under the mouse)"
    assert not view.open_button.isEnabled()  # hovering selects nothing


def test_a_kept_session_opens_and_a_rerun_reproduces_the_row(qtbot, view, small_table, tmp_path):
    folder, rows = small_table
    view.open_table(folder)
    pick(view, "K", "seed")
    i = next(i for i, r in enumerate(rows) if r["status"] == "ok" and r["K"] == 50.0)
    qtbot.mouseClick(view.plot.viewport(), QtCore.Qt.MouseButton.LeftButton,
                     pos=spot_pos(qtbot, view, i))
    assert view.selected == i
    assert view.open_button.isEnabled() and view.rerun_button.isEnabled()
    with qtbot.waitSignal(view.session_requested, timeout=5000) as sig:
        view.open_button.click()
    assert sig.args == [rows[i]["session"]] and looks_like_session(sig.args[0])

    with qtbot.waitSignal(view.session_requested, timeout=RUN_TIMEOUT_MS) as sig:
        view.rerun_button.click()
        assert not view.rerun_button.isEnabled()  # one re-run at a time
    path = sig.args[0]
    assert os.path.dirname(path) == str(tmp_path / "sessions") and looks_like_session(path)
    assert "its row equals the table's (times aside)" in view.note.text()
    assert view.rerun_button.isEnabled()


def test_refused_points_and_analysis_sweeps(qtbot, view, small_table, tmp_path):
    folder, rows = small_table
    view.open_table(folder)
    refused = next(i for i, r in enumerate(rows) if r["status"] == "refused")
    view.select(refused)
    assert not view.open_button.isEnabled()  # refused before its start record: no session
    asked = []
    view.session_requested.connect(asked.append)
    view.rerun_button.click()
    qtbot.waitUntil(lambda: view.rerun_button.isEnabled(), timeout=RUN_TIMEOUT_MS)
    assert asked == []
    assert "refused" in view.note.text() and "no session recorded" in view.note.text()

    a = run_sweep(spec_from_dict({"sweep": {"kind": "analysis", "analysis": "etfe"},
                                  "fixed": {"n": 2000}, "grid": {"seed": [1, 2]}}),
                  tmp_path / "a.sweep", workers=0)
    assert view.open_table(a.table)
    view.select(0)
    assert not view.rerun_button.isEnabled() and not view.open_button.isEnabled()


def test_what_is_not_a_table_is_one_line(view, tmp_path):
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "x.txt").write_text("mine")
    assert not view.open_table(tmp_path / "other")
    assert "not a sweep table" in view.note.text() and "\n" not in view.note.text()
    broken = tmp_path / "b.sweep"
    broken.mkdir()
    (broken / "part-0.parquet").write_bytes(b"not parquet")
    assert not view.open_table(broken)
    assert view.note.text() and "\n" not in view.note.text()


def test_the_main_window_replays_a_point_of_its_sweeps_tab(qtbot, tmp_path, small_table):
    folder, rows = small_table
    win = MainWindow(Rig(), tmp_path / "sessions", realtime=False)
    qtbot.addWidget(win)
    win.show()
    win.tabs.setCurrentWidget(win.sweeps)
    assert win.sweeps.open_table(folder)
    i = next(i for i, r in enumerate(rows) if r["status"] == "ok")
    win.sweeps.select(i)
    win.sweeps.open_button.click()
    assert win.mode == "replay"
    qtbot.waitUntil(lambda: win.mode == "idle" and win.live.buffer.n == rows[i]["n_samples"],
                    timeout=RUN_TIMEOUT_MS)
    _start, _desc, channels, *_ = load_session(rows[i]["session"])
    assert np.array_equal(win.live.buffer.channel("position"), channels["position"])
    assert f"replay {os.path.basename(rows[i]['session'])}" in " ".join(win.log.texts("info"))
