"""One truth: every number the window shows for a session equals the report's for it."""
import os

os.environ["QT_QPA_PLATFORM"] = "offscreen"  # before any Qt import

import re  # noqa: E402
from decimal import Decimal  # noqa: E402

import pytest  # noqa: E402

from labbench.gui.id_view import cells  # noqa: E402
from labbench.gui.live_estimate import LIVE as LIVE_ESTIMATOR  # noqa: E402
from labbench.gui.live_view import RUN_PLANT  # noqa: E402
from labbench.gui.main_window import MainWindow  # noqa: E402
from labbench.readout.numfmt import fmt  # noqa: E402
from labbench.report.blocks import Table  # noqa: E402
from labbench.report.content import build  # noqa: E402
from labbench.report.render_html import render_html  # noqa: E402
from labbench.rig import Rig, rig_from_dict  # noqa: E402

RUN_TIMEOUT_MS = 60_000


def _etfe_in_window(qtbot, rig, tmp_path) -> MainWindow:
    """An 8 s ETFE (seed 2) started from the window, finished successfully."""
    win = MainWindow(rig, tmp_path / "sessions", realtime=False)
    qtbot.addWidget(win)
    win.show()
    assert win.live.theory_plant.currentIndex() == RUN_PLANT  # the default: as the report
    win.protocol_panel.choice.setCurrentText("etfe")
    win.protocol_panel.set_value("duration_s", 8.0)
    win.protocol_panel.set_value("seed", 2)
    win.start_protocol()
    qtbot.waitUntil(lambda: win.last_run is not None and win.mode == "idle", timeout=RUN_TIMEOUT_MS)
    assert win.last_run.status == "success", win.last_run.reason
    return win


def _report_html(path) -> str:
    report = build([path])
    return render_html(report.title, report.subtitle, report.blocks)


def _same_number(shown: str, reported: str) -> bool:
    """Two renderings of one number: they differ by less than half a unit in the last
    place of the coarser (the window and the report choose their digits each)."""
    a, b = Decimal(shown), Decimal(reported)
    ulp = max(Decimal(1).scaleb(a.as_tuple().exponent), Decimal(1).scaleb(b.as_tuple().exponent))
    return abs(a - b) <= ulp / 2


def _report_loop_fit(path) -> dict[str, str]:
    """name -> value of the report's closed-loop fit table (its "value (lo to hi)" cells:
    ``labbench.readout.numfmt.fmt_ci``)."""
    table = next(b for b in build([path]).blocks
                 if isinstance(b, Table) and b.title.startswith("Closed-loop fit"))
    return {row[0]: row[1].split(" (")[0] for row in table.rows}


# the default rig, and one whose device has 2 samples of delay that its file states
RIGS = {"no device delay": Rig(),
        "a stated device delay": rig_from_dict({"rig": {"measured_td_s": 0.002},
                                                "sim": {"extra_delay_samples": 2}})}


@pytest.mark.parametrize("rig", list(RIGS))
def test_bandwidths_and_plant_in_the_window_equal_the_reports(qtbot, tmp_path, rig):
    win = _etfe_in_window(qtbot, RIGS[rig], tmp_path)
    qtbot.waitUntil(lambda: win.live.impedance.last is not None and win.live.impedance.last.n_samples == 8000
                    and win.live.impedance.last.estimator != LIVE_ESTIMATOR, timeout=RUN_TIMEOUT_MS)
    html = _report_html(win.session_path)
    bw = win.last_run.results["bandwidths"]
    plant = win.last_run.results["plant"]

    # the marks: measured, the sampled theory, the paper's closed form, as the report's table
    ws, wb = (win.live.impedance.marks[k].label.format.replace("\n", " ") for k in ("ws", "wb"))
    numbers = {k: fmt(bw[k]) for k in bw}
    assert ws == (f"w_s* = {numbers['ws_star_measured']} rad/s (sampled theory "
                  f"{numbers['ws_star_predicted']} rad/s; paper eq. 5: {numbers['ws_star_eq5']})")
    assert wb == (f"w_b* = {numbers['wb_star_measured']} rad/s (sampled theory "
                  f"{numbers['wb_star_predicted']} rad/s; paper w0: {numbers['wb_star_w0']})")
    for sym in ("ws", "wb"):
        measured, predicted = numbers[f"{sym}_star_measured"], numbers[f"{sym}_star_predicted"]
        # page 1, as labbench.readout.wording writes it
        assert f"measured = {measured} rad/s; sampled theory = {predicted} rad/s" in html
    # the wb* the sampled model predicts is far from w0: the window must not call w0 "theory"
    assert bw["wb_star_predicted"] < 0.7 * bw["wb_star_w0"]
    assert "(theory " not in ws + wb

    # the plant of the overlay is the report's "device model of the theory"
    title = win.live.impedance.title.text
    m, b = fmt(plant["m"]), fmt(plant["b"])
    assert f"m = {m} kg, b = {b} N s/m" in title
    assert re.search(rf"m = {re.escape(m)} kg, b = {re.escape(b)} N s/m", html)

    # the closed-loop fit on the Identification tab is the report's
    report, shown = _report_loop_fit(win.session_path), cells(win.id_view.fit_table)
    for name, row in (("m", "mass m"), ("b", "damping b"),
                      ("extra delay td", "device latency td")):
        value = shown[row][0].split(" ")[0]  # "0.094 kg (exact ...)": its number
        assert _same_number(value, report[name]), (name, shown[row][0], report[name])
    win.close()


def test_the_window_says_what_the_cli_and_the_report_say(qtbot, tmp_path):
    # issue 30's third surface: an ETFE run from the window shows the verdict lines and the
    # rendered sentence of the session's readout, which the CLI and the report write
    # (tests/test_readout.py: the CLI's JSON and text, replay and the report agree)
    from labbench.readout import wording
    from labbench.sessions import session_content

    win = _etfe_in_window(qtbot, Rig(), tmp_path)
    qtbot.waitUntil(lambda: bool(win.live.verdicts.shown), timeout=RUN_TIMEOUT_MS)
    back = session_content.readout_of(win.session_path)
    shown = win.live.verdicts
    assert [j.line() for j in shown.shown] == [j.line() for j in back.verdicts]
    text = shown.text()
    assert back.rendered is not None and back.rendered.sentence() in text.replace("&amp;", "&")
    html = _report_html(win.session_path)
    for j in shown.shown:
        assert j.verdict.line() in html
    win.close()
