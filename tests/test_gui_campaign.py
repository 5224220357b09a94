"""The Campaign page as a person uses it: open a spec, read the plan, Start, watch the rows
and the chart fill in, Stop and Start again (the stopped point runs again), open a point's
session; E-STOP ends a campaign like a run."""
import os

os.environ["QT_QPA_PLATFORM"] = "offscreen"  # before any Qt import

import json  # noqa: E402

import pytest  # noqa: E402

from labbench.gui.main_window import MainWindow  # noqa: E402
from labbench.rig import Rig  # noqa: E402
from labbench.sweep import table as tables  # noqa: E402

SPEC = ('[sweep]\nname = "k"\nprotocol = "etfe"\n[fixed]\nve = "spring"\nduration_s = {d}\n'
        'seed = 3\n[grid]\nK = [10.0, 20.0, 30.0]\n')


@pytest.fixture
def win(qtbot, tmp_path):
    w = MainWindow(Rig(), tmp_path / "sessions", realtime=True)
    qtbot.addWidget(w)
    w.show()
    return w


def spec_file(tmp_path, duration_s):
    p = tmp_path / "k.toml"
    p.write_text(SPEC.format(d=duration_s))
    return p


def test_the_campaign_page_plans_with_the_chirp_ids_friction(win, tmp_path):
    """The page's probes take the Coulomb term of the chirp-ID that gave their plant, as
    ``labbench campaign`` does (before: only the commissioning's; none here)."""
    p = tmp_path / "zw.toml"
    p.write_text('[sweep]\nname = "zw"\nprotocol = "stability"\n[fixed]\nve = "spring-damper"\n'
                 'w0_rad_s = 125.0\nK_frac_k_max = 0.8\n[grid]\nB = [0.0, 1.0]\n')
    win.identified = {"m": 0.094, "b": 0.1, "session": str(tmp_path / "x_chirp-id.lbsession"),
                      "coulomb_n": 0.02, "coulomb_ci95": [0.019, 0.021]}
    win.campaign.open_requested.emit(str(p))
    points = win.campaign_plan.points
    assert [pp.options["plant_coulomb_n"] for pp in points] == [0.02, 0.02]
    assert points[0].options["plant_m_kg"] == 0.094


def test_a_campaign_from_the_page_stopped_and_resumed(qtbot, win, tmp_path):
    page = win.campaign
    assert not page.start_button.isEnabled()  # no plan yet
    page.open_requested.emit(str(spec_file(tmp_path, 1.5)))
    assert "3 points, 0 already" in page.plan_label.text() and "3 to run" in page.plan_label.text()
    assert "largest force planned" in page.plan_label.text()
    assert page.start_button.isEnabled() and not page.stop_button.isEnabled()

    page.start_button.click()
    assert page.stop_button.isEnabled() and not page.start_button.isEnabled()
    assert not win.protocol_panel.start_button.isEnabled()  # no other run meanwhile
    assert win.loop_status is not None and win.state.name in ("campaign", "running")
    # the first row arrives; stop during the second point
    qtbot.waitUntil(lambda: page.table.rowCount() == 1, timeout=60_000)
    qtbot.waitUntil(lambda: win.mode == "running", timeout=30_000)
    page.stop_button.click()
    qtbot.waitUntil(lambda: not page.running, timeout=30_000)
    assert "stopped" in page.state_label.text()
    assert page.start_button.isEnabled() and win.protocol_panel.start_button.isEnabled()
    table = win.campaign_table
    assert [r["K"] for r in tables.read_table(table).to_pylist()] == [10.0]
    attempts = json.loads((table / "_attempts.json").read_text())
    assert len(attempts) == 1  # the stopped point, to run again

    # Start again: the stopped point and the last one; all three rows, the second twice tried
    page.open_requested.emit(str(spec_file(tmp_path, 1.5)))
    assert "1 already" in page.plan_label.text()
    page.start_button.click()
    qtbot.waitUntil(lambda: not page.running, timeout=120_000)
    assert "complete" in page.state_label.text(), page.state_label.text()
    rows = tables.read_table(table).to_pylist()
    assert [r["attempts"] for r in rows] == [1, 2, 1] and all(r["status"] == "ok" for r in rows)
    qtbot.waitUntil(lambda: page.table.rowCount() == 3, timeout=20_000)
    assert page.table.item(1, 2).text() == "ok"

    # open a point's session: it is replayed in the Live view
    page.table.selectRow(2)
    assert page.session_button.isEnabled()
    page.session_button.click()
    qtbot.waitUntil(lambda: win.mode == "idle" and win._replay_path == rows[2]["session"],
                    timeout=30_000)


def test_the_zwidth_chart_fills_in_and_estop_ends_the_campaign(qtbot, win, tmp_path):
    page = win.campaign
    p = tmp_path / "zw.toml"
    p.write_text('[sweep]\nname = "zw"\nprotocol = "stability"\n[fixed]\nve = "spring-damper"\n'
                 'w0_rad_s = 125.0\nK_frac_k_max = 0.8\nrefine_s = 3.0\n[grid]\n'
                 'B = [0.0, 1.0, 2.0]\n')
    page.open_requested.emit(str(p))
    page.start_button.click()
    qtbot.waitUntil(lambda: page.table.rowCount() >= 1 and bool(page.chart.points), timeout=120_000)
    assert "K_max" in page.table.item(0, 3).text()
    # the chart is live (issue 43: a 430 x 300 bitmap with 6 px text): a point under the mouse
    # names its row under the chart, a click selects it in the table
    assert page.chart.kind == "zwidth"
    item = page.chart.points[0]
    spot = item.points()[0]
    item.sigHovered.emit(item, [spot], None)
    assert page.chart.caption.text().startswith(f"#: {page.rows[spot.data()]['index']}; point: B = ")
    item.sigClicked.emit(item, [spot], None)
    assert page.selected_session() == page.rows[spot.data()].get("session")
    qtbot.waitUntil(lambda: win.mode == "running", timeout=30_000)
    win.emergency_stop()
    qtbot.waitUntil(lambda: not page.running, timeout=30_000)
    assert "E-STOP" in page.state_label.text()
    assert win.state.latched and not page.start_button.isEnabled()  # as after any run
