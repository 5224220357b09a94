"""The Campaign page as a person uses it: open a spec, read the plan, Start, watch the rows
and the chart fill in, Stop and Start again (the stopped point runs again), open a point's
session; E-STOP ends a campaign like a run."""
import os

os.environ["QT_QPA_PLATFORM"] = "offscreen"  # before any Qt import

import json  # noqa: E402

import numpy as np  # noqa: E402
import pyqtgraph as pg  # noqa: E402

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


def _zwidth_rows() -> list[dict]:
    """A Z-width table's rows as the campaign writes them (every column in every row, None
    where a point has nothing): two filters; per filter a point above the passive bound, one
    within it, one where no step grew, one that failed; the friction known (a plan, and a
    friction-aware boundary with its range at two points)."""
    from labbench.model.pulse import PulsePlan

    plan = json.dumps({"coulomb_n": 0.02, "friction_cap": 3.0, "pulse": PulsePlan(
        0.3, 0.01, 5.0, 0.02, 1.0).as_dict()}, sort_keys=True)
    rows = []
    for w0 in (125.0, 250.0):
        for B, k, above, status, passive in ((1.0, 1200.0, None, "ok", 300.0),
                                             (0.0, 200.0, None, "ok", 250.0),
                                             (2.0, None, 1800.0, "ok", 100.0),
                                             (0.5, None, None, "failed", 200.0)):
            rows.append({
                "index": len(rows), "status": status, "session": f"s{len(rows)}.lbsession",
                "device": "sim", "rig.name": "bench", "rig.sample_time_s": 1e-3,
                "rig.device_delay_s": 0.0, "rig.metres_per_count": 3.8e-5,
                "rig.counts_per_rev": 16384, "plant.m": 0.094, "plant.b": 0.1,
                "plant.from": "nominal", "commission.session": None, "commission.coulomb_n": None,
                "ve.B": B, "ve.w0_rad_s": w0, "ve.td_s": 0.0,
                "zw.k_max": k, "zw.ci_lo": None if k is None else 0.97 * k,
                "zw.ci_hi": None if k is None else 1.02 * k, "zw.k_max_above": above,
                "zw.k_friction": 0.9 * k if k else None,
                "zw.k_friction_lo": 0.85 * k if k else None,
                "zw.k_friction_hi": 0.95 * k if k else None,
                "pred.k_max": 1000.0 * B + 200.0 + w0, "pred.k_passive": passive,
                "pred.k_passive_quantised": 150.0, "pred.k_max_friction_plan": plan})
    return rows


def _rate_rows() -> list[dict]:
    """A rate study's rows, not in the order of their sample times (the chart sorts them;
    each point must still name its own row)."""
    rows = []
    for n, T in enumerate((2e-3, 5e-4, 4e-3, 1e-3)):
        s = 1e3 * T
        rows.append({"index": n, "status": "ok", "session": f"r{n}.lbsession", "device": "sim",
                     "rig.sample_time_s": T, "ve.kind": "spring-damper", "ve.K": 50.0,
                     "ve.B": 1.0, "ve.w0_rad_s": 125.0,
                     **{f"{src}.{w}_{stat}": f * s * (1.1 if src == "acc" else 1.0)
                        for src in ("acc", "pred") for w, f in (("ed", 0.02), ("es", 0.01))
                        for stat in ("median", "max")},
                     "res.bandwidths.ws_star_predicted": 24.0, "res.bandwidths.ws_star_measured": 24.5,
                     "res.bandwidths.wb_star_predicted": 80 / s, "res.bandwidths.wb_star_measured": 78 / s,
                     "pred.k_max": 1200 / s, "acc.k_max_fit": 1190 / s})
    return rows


@pytest.mark.parametrize("rows, make", [(_zwidth_rows, "zwidth_figure"), (_rate_rows, "rate_figure")])
def test_the_page_draws_every_panel_and_point_of_the_campaigns_own_figure(qtbot, rows, make):
    """The page drew only the first panel of the campaign's figure (for a Z-width its
    measured points and exact line; for a rate study the ED median of its four panels);
    the PNG the CLI writes (``labbench.campaign.figures``) has more. Every labelled line,
    point set and level of every panel of the PNG's figure is on the page with the same
    points (errors bars too), each point naming its row; the chart fills in as rows come."""
    from labbench.campaign import figures
    from labbench.gui.campaign_chart import CampaignChart

    rows = rows()
    cols = {name: [r.get(name) for r in rows] for name in {k for r in rows for k in r}}
    fig = getattr(figures, make)(cols)
    chart = CampaignChart()
    qtbot.addWidget(chart)
    chart.show(figures.charts(rows[:2]), rows[:2])
    first = sum(len(p.points()) for p in chart.points)
    chart.show(figures.charts(rows), rows)
    assert sum(len(p.points()) for p in chart.points) > first  # filled in as rows came
    assert len(chart.plots) == len(fig.axes)
    for k, ax in enumerate(fig.axes):
        page = chart.shown(k)
        lines = [ln for ln in ax.get_lines() if not ln.get_label().startswith("_")]
        assert [ln.get_label() for ln in lines] == [label for label, *_ in page] and len(page) >= 2
        for ln, (label, kind, px, py) in zip(lines, page):
            x, y = (np.asarray(v, float) for v in ln.get_data())
            if kind == "level":  # matplotlib's axhline: x 0..1 of the axes, y its level
                assert list(x) == [0, 1] and np.allclose(py, y), label
                continue
            keep = np.isfinite(x) & np.isfinite(y)
            assert np.allclose(px, x[keep]) and np.allclose(py, y[keep]), label
        bars = sorted(tuple(np.round([s[0][0], *sorted((s[0][1], s[1][1]))], 6))
                      for c in ax.collections for s in c.get_segments())
        on_page = sorted(tuple(np.round([x, y - b, y + t], 6))
                         for item in chart.plots[k].items if isinstance(item, pg.ErrorBarItem)
                         for x, y, t, b in zip(*(item.opts[o] for o in ("x", "y", "top", "bottom"))))
        assert on_page == bars
    # each point names its row: under the mouse the row, and its x is the row's
    seen = set()
    for item in chart.points:
        for spot in item.points():
            chart.row_hovered.connect(seen.add)
            item.sigHovered.emit(item, [spot], None)
            chart.row_hovered.disconnect(seen.add)
            r = rows[spot.data()]
            panel = chart.panels[chart.plots.index(item.getViewBox().parentItem())]
            x = 10 ** spot.pos().x() if panel.xlog else spot.pos().x()
            assert x == pytest.approx(r["ve.B"] if make == "zwidth_figure" else 1e3 * r["rig.sample_time_s"])
    assert seen == set(range(len(rows)))
