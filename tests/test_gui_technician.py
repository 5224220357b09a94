"""Issue 31: the window as a technician uses it. Each test drives one of the issue's
defects as a person meets it (clicks, keys, dialogs) and asserts what is on screen after."""
import os

os.environ["QT_QPA_PLATFORM"] = "offscreen"  # before any Qt import

import functools  # noqa: E402

import pytest  # noqa: E402
from PySide6 import QtCore, QtWidgets  # noqa: E402

from labbench.gui.device_panel import FROM_RIG  # noqa: E402
from labbench.gui.main_window import NO_CAN, NO_PORT, MainWindow  # noqa: E402
from labbench.registry import open_device  # noqa: E402
from labbench.rig import Rig  # noqa: E402

SIM_AS_HARDWARE = functools.partial(open_device, "sim")  # the simulator behind a real backend's name

RUN_MS = 120_000


@pytest.fixture
def window(qtbot, tmp_path):
    def make(rig=None, realtime=False, **options):
        win = MainWindow(rig or Rig(), tmp_path / "sessions", realtime=realtime, **options)
        qtbot.addWidget(win)
        win.show()
        return win

    return make


def _connect(qtbot, win):
    win.device_panel.connect_button.click()
    qtbot.waitUntil(lambda: win.device is not None, timeout=30_000)


def _in_modal(qtbot, act):
    """Call ``act(dialog)`` once a modal dialog is up (a file dialog's exec returns only when
    it closes, so the test's clicks inside it run from the event loop); what it raised is
    returned in the list, and a dialog it left open is cancelled."""
    raised = []

    def poll():
        dialog = QtWidgets.QApplication.activeModalWidget()
        if dialog is None:
            QtCore.QTimer.singleShot(20, poll)
            return
        try:
            act(dialog)
        except BaseException as exc:  # noqa: BLE001 - reported by the test after exec returns
            raised.append(exc)
        if dialog.isVisible():
            dialog.reject()

    QtCore.QTimer.singleShot(0, poll)
    return raised


def _completion_popup(qtbot, dialog, typed: str):
    """Type ``typed`` into the file dialog's name field until its completion list shows (the
    path up to its last letter put in at once: the field reads a typed "/" as a new name)."""
    edit = dialog.findChild(QtWidgets.QLineEdit, "fileNameEdit")
    edit.setFocus()
    edit.setText(typed[:-1])
    qtbot.keyClicks(edit, typed[-1])
    popup = edit.completer().popup()
    qtbot.waitUntil(popup.isVisible, timeout=10_000)
    return edit, popup


# ----- defect 2: one Esc rule, in dialogs and pop-up lists too -------------------------------
def test_esc_is_estop_inside_a_dialog_and_its_completion_list(qtbot, window, tmp_path):
    (tmp_path / "specs-here").mkdir()
    win = window()
    assert "once a device is connected" in win.keys_hint.text()
    _connect(qtbot, win)
    assert "E-STOP: Esc everywhere" in win.keys_hint.text()  # the rule in force, on screen
    win.tabs.setCurrentWidget(win.sweeps)
    seen = {}

    def inside(dialog):
        edit, popup = _completion_popup(qtbot, dialog, f"{tmp_path}/spec")
        qtbot.keyClick(popup, QtCore.Qt.Key.Key_Escape)  # the list has the keyboard
        seen["latched in list"] = win.estop.latched
        seen["dialog open after list Esc"] = dialog.isVisible()
        popup.hide()  # the list closed by clicking away
        qtbot.keyClick(edit, QtCore.Qt.Key.Key_Escape)  # the dialog itself
        seen["dialog open after Esc"] = dialog.isVisible()
        seen["estops"] = sum("E-STOP: force zeroed" in t for t in win.log.texts("warning"))

    raised = _in_modal(qtbot, inside)
    win.sweeps.open_table_button.click()  # returns when the dialog has closed
    assert not raised, raised
    assert seen == {"latched in list": True, "dialog open after list Esc": True,
                    "dialog open after Esc": True, "estops": 2}
    assert "LATCHED" in win.estop.text() and win.mode == "idle"
    qtbot.waitUntil(lambda: win.estop_confirmed, timeout=10_000)  # the device's own stop

    # a drop-down list of the main window: the same
    win.device_panel.connect_button.click()  # Disconnect clears the latch ...
    _connect(qtbot, win)  # ... and a new connection arms the keys again
    combo = win.protocol_panel.choice
    combo.showPopup()
    qtbot.waitUntil(lambda: combo.view().isVisible(), timeout=5_000)
    qtbot.keyClick(combo.view(), QtCore.Qt.Key.Key_Escape)
    assert win.estop.latched
    combo.hidePopup()


def test_without_a_device_esc_keeps_its_usual_meaning(qtbot, window, tmp_path):
    (tmp_path / "specs-here").mkdir()
    win = window()
    win.tabs.setCurrentWidget(win.sweeps)
    seen = {}

    def inside(dialog):
        edit, popup = _completion_popup(qtbot, dialog, f"{tmp_path}/spec")
        qtbot.keyClick(popup, QtCore.Qt.Key.Key_Escape)
        seen["list closed"] = not popup.isVisible()
        seen["dialog open"] = dialog.isVisible()
        qtbot.keyClick(edit, QtCore.Qt.Key.Key_Escape)
        seen["dialog closed"] = not dialog.isVisible()

    raised = _in_modal(qtbot, inside)
    win.sweeps.open_table_button.click()
    assert not raised, raised
    assert seen == {"list closed": True, "dialog open": True, "dialog closed": True}
    assert not win.estop.latched and not any("E-STOP" in t for t in win.log.texts())


def test_space_types_in_a_text_field_and_stops_elsewhere(qtbot, window):
    win = window()
    _connect(qtbot, win)
    field = win.protocol_panel.form.fields["duration_s"].widget
    field.setFocus()
    field.clear()
    qtbot.keyClicks(field, "1 2")
    assert field.text() == "1 2" and not win.estop.latched  # typed, not a stop
    win.protocol_panel.start_button.setFocus()
    qtbot.keyClick(win.protocol_panel.start_button, QtCore.Qt.Key.Key_Space)
    assert win.estop.latched and win.mode == "idle"  # a stop, not a click on Start


# ----- defect 9: the Sweeps tab runs a spec -----------------------------------------------------
SPEC = """[sweep]
name = "springs"
protocol = "etfe"

[fixed]
duration_s = 1.0

[grid]
K = [20.0, 50.0, 80.0, 110.0]
seed = [1, 2]
"""


def test_the_sweeps_tab_runs_a_spec_with_progress_cancel_and_resume(qtbot, window, tmp_path):
    from labbench.sweep.table import done_keys

    spec = tmp_path / "springs.toml"
    spec.write_text(SPEC)
    win = window()
    view = win.sweeps
    win.tabs.setCurrentWidget(view)
    assert not view.run_button.isEnabled() and "Open spec" in view.table_label.text()
    raised = _in_modal(qtbot, lambda d: (d.selectFile(str(spec)), d.accept()))
    view.open_spec_button.click()
    assert not raised, raised
    assert "8 points of run etfe" in view.table_label.text() and view.run_button.isEnabled()
    table = tmp_path / "sweeps" / "springs.sweep"  # beside the sessions folder, as the CLI's
    assert str(table) in view.table_label.text()

    view.workers.setValue(0)  # computed in the sweep's own process, no Dask cluster
    view.run_button.click()
    assert not view.run_button.isEnabled() and view.cancel_button.isEnabled()
    qtbot.waitUntil(lambda: view.progress.value() > 0, timeout=RUN_MS)
    view.cancel_button.click()
    qtbot.waitUntil(lambda: view.run is None, timeout=RUN_MS)
    first = len(done_keys(table))
    assert 0 < first < 8
    assert "stopped" in view.progress_text.text() and "Run computes the rest" in view.note.text()
    assert view.progress_text.text().startswith(f"{first} of 8 points")

    view.run_button.click()  # resumes: only the rest is computed
    qtbot.waitUntil(lambda: view.run is None, timeout=RUN_MS)
    assert "complete" in view.progress_text.text() and view.progress.value() == 1000
    assert f"({8 - first} computed now" in view.note.text()
    assert len(done_keys(table)) == 8 and len(view.cols["key"]) == 8

    # default axes: the varied parameter against a varied result, the seed as colour
    assert view.x.currentData() == "K" and view.color.currentData() == "seed"
    y = view.y.currentData()
    assert y.startswith("truth.") and len(set(view.cols[y])) > 1
    bottom = view.plot.getAxis("bottom")
    assert bottom.labelText == "K [N/m]" and not bottom.autoSIPrefix


def test_a_file_that_is_not_a_spec_is_one_line(qtbot, window, tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[sweep]\nname = 3\n")
    view = window().sweeps
    assert not view.open_spec(bad)
    assert str(bad) in view.note.text() and "\n" not in view.note.text()
    assert not view.run_button.isEnabled()


@pytest.mark.parametrize("column, label", [
    ("K", "K [N/m]"),
    ("K_frac_k_max", "K / K_max"),
    ("duration_s", "duration [s]"),
    ("res.loop_fit.ci95.m.0", "loop fit: m, 95 % low [kg]"),
    ("res.loop_fit.ci95.m.n", "loop fit: m, 95 % (count)"),
    ("truth.k_max", "truth: K_max [N/m]"),
    ("truth.median_rel", "truth: median rel (fraction)"),
    ("res.bandwidths.ws_star_measured", "bandwidths: ws* measured [rad/s]"),
    ("noise_seed", "noise seed"),
    ("status", "status"),
])
def test_sweep_columns_are_labelled_with_their_units(column, label):
    from labbench.gui.sweep_view import column_label

    assert column_label(column) == label


# ----- defect 3: the live view shows only what the run can measure -----------------------------
def _drawn(win, key: str):
    """(w, y) of what the effective-impedance curve ``key`` draws (finite points, SI w)."""
    import numpy as np

    w, y = win.live.impedance.curves[key].getOriginalDataset()
    keep = np.isfinite(y)
    return w[keep], y[keep]


def _legend(plots) -> list[str]:
    return [label.text for _sample, label in plots.legend.items]


def test_a_chirp_shows_only_the_frequencies_it_has_reached_and_no_ve_marks(qtbot, window):
    import numpy as np

    win = window(realtime=True, rig=Rig(sections={"safety": {"watchdog_s": 1.0}}))
    f0, f1, T = 0.2, 25.0, 10.0
    win.protocol_panel.choice.setCurrentText("chirp-id")
    for name, value in (("f0_hz", f0), ("f1_hz", f1), ("duration_s", T)):
        win.protocol_panel.set_value(name, value)
    seen = []

    def watch():  # every estimate drawn while the chirp runs: what it drew, and when
        est = win.live.impedance.last
        if win.mode == "running" and est is not None and (not seen or seen[-1][0] != est.n_samples):
            seen.append((est.n_samples, *_drawn(win, "ED")))
        return win.mode == "idle" and win.last_run is not None

    win.protocol_panel.start_button.click()
    qtbot.waitUntil(watch, timeout=RUN_MS)
    assert win.last_run.status == "success", win.last_run.reason
    assert len(seen) >= 4, seen
    for n, w, _ed in seen:  # the log sweep's frequency when the estimate's data ended
        reached = 2 * np.pi * f0 * (f1 / f0) ** (n / 1000 / T)
        # within the window's leakage: 5 bins of the shortest segment (2048 samples)
        assert w.size == 0 or w.max() <= max(1.5 * reached, reached + 15.0), (n, w.max(), reached)
    assert any(w.size for _n, w, _ed in seen)  # something drawn before the end
    qtbot.waitUntil(lambda: win.live.impedance.last is not None
                    and win.live.impedance.last.n_samples == win.live.buffer.n
                    and win.live.impedance.last.estimator != "live-welch", timeout=RUN_MS)
    plots = win.live.impedance
    w, _ = _drawn(win, "ED")
    assert w.max() <= 1.5 * 2 * np.pi * f1  # the chirp's top, not the leakage above it
    assert "not excited" in plots.title.text
    # VE off: no stiffness or damping bandwidth to mark
    assert not plots.marks["ws"].isVisible() and not plots.marks["wb"].isVisible()
    # the legend names what is drawn: the theory (the plant's own Z) only with its curve
    theory_drawn = np.isfinite(plots.curves["ED_theory"].getOriginalDataset()[1]).any()
    assert ("theory (exact sampled model)" in _legend(plots)) == theory_drawn


def test_a_white_noise_etfe_is_drawn_whole_with_its_marks(qtbot, window):
    import numpy as np

    win = window()
    win.protocol_panel.choice.setCurrentText("etfe")
    win.protocol_panel.set_value("duration_s", 6.0)
    win.protocol_panel.start_button.click()
    qtbot.waitUntil(lambda: win.mode == "idle" and win.last_run is not None, timeout=RUN_MS)
    qtbot.waitUntil(lambda: win.live.impedance.last is not None
                    and win.live.impedance.last.n_samples == win.live.buffer.n
                    and win.live.impedance.last.estimator != "live-welch", timeout=RUN_MS)
    est, plots = win.live.impedance.last, win.live.impedance
    shown = (est.w > 0) & (est.w <= est.w_nyquist / 3)
    assert est.excited[shown].all()  # white noise reaches every frequency: nothing masked
    assert "not excited" not in plots.title.text
    assert plots.marks["ws"].isVisible() and plots.marks["wb"].isVisible()
    assert _legend(plots) == ["measured (ETFE), 95 % band", "theory (exact sampled model)"]
    plots.setCurrentIndex(1)  # the Bode tab has a legend too
    assert [label.text for _s, label in plots.bode_legend.items] == [
        "measured (ETFE)", "theory (exact sampled model)"]
    assert np.isfinite(plots.curves["bode_mag"].getOriginalDataset()[1]).all()
    # issue 30: the damping axis shows the rendered damping (B + b = 1.1 N s/m below w_b*)
    # readably, not the roll-off to about -50 N s/m near Nyquist, which leaves the axes
    lo, hi = plots.plots["ED"].getViewBox().viewRange()[1]
    assert lo <= 0.0 and 1.1 < hi < 3.0 and hi - lo < 5.0, (lo, hi)
    assert np.nanmin(plots.curves["ED"].getOriginalDataset()[1]) < lo  # drawn, beyond the axes


# ----- defect 7: nothing stale left on screen --------------------------------------------------
def _run(qtbot, win, protocol, **settings):
    win.last_run = None
    win.protocol_panel.choice.setCurrentText(protocol)
    for name, value in settings.items():
        win.protocol_panel.set_value(name, value)
    win.protocol_panel.start_button.click()
    qtbot.waitUntil(lambda: win.mode == "idle" and win.last_run is not None, timeout=RUN_MS)
    assert win.last_run.status == "success", win.last_run.reason
    return win.session_path


def _sessions_listed(qtbot, win, n):
    qtbot.waitUntil(lambda: len(win.sessions.paths) == n, timeout=20_000)


def test_reanalyse_shows_the_records_traces_and_axes_and_replay_ends_full(qtbot, window):
    import numpy as np

    win = window()
    chirp = _run(qtbot, win, "chirp-id", f0_hz=1.0, duration_s=4.0)  # a narrow record
    _run(qtbot, win, "etfe", duration_s=30.0, seed=1)  # then a long, wide one
    _sessions_listed(qtbot, win, 2)
    es = win.live.impedance.plots["ES"].getViewBox()
    qtbot.waitUntil(lambda: win.live.impedance.last is not None
                    and win.live.impedance.last.n_samples == 30_000, timeout=RUN_MS)
    wide = es.viewRange()[0]

    win.tabs.setCurrentWidget(win.sessions)
    win.sessions.select_path(chirp)
    win.sessions.buttons["Re-analyse"].click()
    qtbot.waitUntil(lambda: "re-analysis of" in win.sessions.progress_line.text()
                    and win.sessions.cancel_button.isEnabled() is False, timeout=RUN_MS)
    assert win.tabs.currentWidget() is win.live
    # the traces are the chirp's, the header counts its samples
    assert win.live.buffer.n == 4000 and "from 4000 samples" in win.live.impedance.title.text
    x, y = win.live.traces.curves["position"].getOriginalDataset()
    assert x.size > 0 and np.isfinite(y).all()
    # the frequency axis spans the chirp's estimate, not the 30 s ETFE's wider one
    w, _ = win.live.impedance.curves["ED"].getOriginalDataset()
    lo, hi = np.log10(w[w > 0].min()), np.log10(w.max())
    def spans_the_chirp():  # the range is set when the plot is next drawn
        x0, x1 = es.viewRange()[0]
        return x0 > wide[0] and x1 - x0 <= 1.2 * (hi - lo) + 0.2

    qtbot.waitUntil(spans_the_chirp, timeout=5000)
    assert win.sessions.progress.value() == 1000

    # Replay fast: the bar full at completion, under "replay completed"
    win.sessions.buttons["Replay fast"].click()
    qtbot.waitUntil(lambda: win.mode == "idle" and win.live.buffer.stop is not None, timeout=RUN_MS)
    assert win.protocol_panel.time_left.text() == "replay completed"
    assert win.protocol_panel.progress.value() == 1000


def test_the_log_follows_after_long_entries_and_always_shows_an_estop(qtbot, window):
    win = window()
    _connect(qtbot, win)
    log, bar = win.log, win.log.verticalScrollBar()
    for i in range(40):  # tables of results, as after runs: the log keeps following
        log.add("info", f"results {i}:", rows=[(f"row {j}", str(j)) for j in range(12)])
        assert log.following() and bar.value() == bar.maximum()
    bar.setValue(0)  # the person scrolls up to read: it stays there ...
    log.add("info", "another table:", rows=[("a", "1")] * 12)
    assert bar.value() == 0 and not log.following()
    win.activateWindow()
    qtbot.keyClick(win, QtCore.Qt.Key.Key_Escape)  # ... but an E-STOP is brought into view
    assert bar.value() == bar.maximum() and log.following()
    assert "E-STOP" in log.toPlainText().splitlines()[-1]


# ----- section "long analyses": progress, cancel, and no silent replacement ---------------------
def test_a_reanalysis_shows_progress_can_be_cancelled_and_never_replaces_a_good_fit(
        qtbot, window, monkeypatch):
    from labbench.gui import jobs
    from labbench.gui.id_view import cells

    win = window()
    path = _run(qtbot, win, "etfe", duration_s=20.0, seed=3)
    _sessions_listed(qtbot, win, 1)
    fit_before = cells(win.id_view.fit_table)
    source_before = win.id_view.fit_source.text()
    assert "the run's own analysis" in source_before

    # cancel: the window keeps what it showed
    phrases = []
    win.sessions.select_path(path)
    win.sessions.estimator.setCurrentText("lpm")
    win.sessions.buttons["Re-analyse"].click()
    assert win.sessions.cancel_button.isEnabled() and not win.sessions.buttons["Re-analyse"].isEnabled()
    qtbot.waitUntil(lambda: phrases.append(win.sessions.progress_line.text())
                    or win.sessions.progress.value() > 0, timeout=RUN_MS)
    win.sessions.cancel_button.click()
    qtbot.waitUntil(lambda: "cancelled" in win.sessions.progress_line.text(), timeout=RUN_MS)
    assert cells(win.id_view.fit_table) == fit_before and win.id_view.fit_source.text() == source_before
    assert win.sessions.buttons["Re-analyse"].isEnabled() and not win.sessions.cancel_button.isEnabled()
    assert any("re-analysing" in p for p in phrases)

    # a re-analysis whose loop fit fails (injected) leaves the good fit shown, and says so
    real = jobs.analyze_etfe

    def failing_fit(*args, **kwargs):
        out = real(*args, **kwargs)
        return {**out, "fit": {"error": "too few coherent frequencies (injected)"}}

    monkeypatch.setattr(jobs, "analyze_etfe", failing_fit)
    win.sessions.estimator.setCurrentText("default")
    win.sessions.buttons["Re-analyse"].click()
    qtbot.waitUntil(lambda: "done" in win.sessions.progress_line.text(), timeout=RUN_MS)
    assert cells(win.id_view.fit_table) == fit_before and win.id_view.fit_source.text() == source_before
    shown = win.live.verdicts.text()
    assert "not replaced: closed-loop fit failed: too few coherent frequencies (injected)" in shown
    assert "not replaced" in win.sessions.progress_line.text()
    assert any("not replaced" in t for t in win.log.texts("warning"))


def test_a_number_in_the_filter_matches_whole_numbers_not_a_timestamp():
    # "200" typed at 20:05 also showed every session whose file was stamped 20:05 (CI, 20:0x)
    from labbench.gui.sessions_view import matches

    row = ("2026-12-04 20:05:12", "etfe", "sim", "spring-damper", "50", "1", "2.0", "success", "ok",
           "2000", "default", "etfe-20261204-200512.lbsession")
    assert not matches(row, ["200"]) and not matches(row, ["etfe", "200"])
    assert matches(row, ["50"]) and matches(row, ["2026"]) and matches(row, ["etfe", "50"])
    assert matches(row, ["spring"]) and matches(row, ["2000"]) and not matches(row, ["512"])


# ----- defect 8: sessions told apart, and filtered ------------------------------------------------
def test_sessions_show_ve_k_b_duration_and_verdict_and_filter(qtbot, window):
    from labbench.gui.sessions_view import COLUMNS

    win = window()
    _run(qtbot, win, "chirp-id", f0_hz=1.0, duration_s=3.0)
    _run(qtbot, win, "etfe", duration_s=2.0, K=50.0)
    _run(qtbot, win, "etfe", duration_s=3.0, K=200.0, B=0.5)
    win.protocol_panel.set_value("K", 5000.0)
    win.protocol_panel.start_button.click()  # refused: no session
    assert "refusing unstable" in win.banner.text()
    _sessions_listed(qtbot, win, 3)
    win.tabs.setCurrentWidget(win.sessions)
    col = {name: i for i, name in enumerate(COLUMNS)}
    rows = {(r[col["protocol"]], r[col["K [N/m]"]]): r for r in win.sessions.shown_rows()}
    assert set(rows) == {("chirp-id", ""), ("etfe", "50"), ("etfe", "200")}
    chirp, k50, k200 = rows[("chirp-id", "")], rows[("etfe", "50")], rows[("etfe", "200")]
    assert chirp[col["VE"]] == "none" and chirp[col["B [N s/m]"]] == ""  # open loop: no K, B
    assert {r[col["device"]] for r in rows.values()} == {"sim"}  # the backend each ran on
    assert (k50[col["VE"]], k50[col["B [N s/m]"]], k50[col["duration [s]"]]) == ("spring-damper", "1", "2.0")
    assert (k200[col["B [N s/m]"]], k200[col["duration [s]"]]) == ("0.5", "3.0")
    for r in (chirp, k50, k200):
        assert r[col["verdict"]] in ("ok", "doubtful", "failed")
    win.sessions.filter.setText("etfe 200")
    assert [r[col["K [N/m]"]] for r in win.sessions.shown_rows()] == ["200"]
    assert win.sessions.count.text() == "1 of 3 sessions"
    assert win.sessions.selected() == win.sessions.paths[
        next(i for i in range(3) if not win.sessions.table.isRowHidden(i))]
    win.sessions.filter.setText("chirp")
    assert [r[col["protocol"]] for r in win.sessions.shown_rows()] == ["chirp-id"]
    win.sessions.filter.clear()
    assert len(win.sessions.shown_rows()) == 3 and win.sessions.count.text() == "3 sessions"


# ----- defect 4: a first-run path on screen that follows the rig ---------------------------------
def _next(win) -> str:
    return win.guide.line.text()


def test_the_first_run_path_says_what_to_do_next_and_follows_the_rig(qtbot, window):
    win = window()
    assert win.guide.isVisible() and win.guide.next_step() == "connect"
    assert "next: Connect" in _next(win) and "Connect in the Device panel" in _next(win)
    # chirp-id preselected: its pre-check says the VE is off, not a spectral radius of "none"
    assert win.protocol_panel.name == "chirp-id"
    assert "VE off (open loop)" in win.protocol_panel.precheck.text()
    assert "spectral radius" not in win.protocol_panel.precheck.text()
    win.guide.buttons["connect"].click()  # the step's button does what it says
    qtbot.waitUntil(lambda: win.device is not None, timeout=30_000)
    # a simulator needs no commissioning: identify is next
    assert win.guide.next_step() == "identify" and "chirp-id" in _next(win)
    assert "not needed on a simulator" in win.guide.buttons["commission"].toolTip()
    win.protocol_panel.choice.setCurrentText("etfe")
    win.tabs.setCurrentWidget(win.sessions)
    win.guide.buttons["identify"].click()  # chooses chirp-id and shows Live; starts nothing
    assert win.protocol_panel.name == "chirp-id" and win.tabs.currentWidget() is win.live
    assert win.mode == "idle" and win.last_run is None
    _run(qtbot, win, "chirp-id", f0_hz=1.0, duration_s=3.0)
    qtbot.waitUntil(lambda: win.guide.next_step() == "measure", timeout=20_000)
    assert "identified in" in win.guide.buttons["identify"].toolTip()
    win.guide.buttons["measure"].click()
    assert win.protocol_panel.name == "etfe" and win.mode == "idle"
    _run(qtbot, win, "etfe", duration_s=2.0)
    qtbot.waitUntil(lambda: win.guide.next_step() is None, timeout=20_000)
    assert "every step done" in _next(win)


def test_on_real_hardware_commissioning_is_the_step_after_connect(qtbot, window, tmp_path):
    from labbench.rig import load_rig

    rig = tmp_path / "bench.toml"
    rig.write_text('[rig]\nname = "bench"\n')
    win = window(rig=load_rig(rig))
    win.device_panel.backend.setCurrentText("canopen")
    win.connect_device("canopen", opener=SIM_AS_HARDWARE)
    qtbot.waitUntil(lambda: win.device is not None, timeout=30_000)
    assert win.guide.next_step() == "commission" and "Commissioning tab" in _next(win)
    chosen = win.protocol_panel.name
    win.guide.buttons["commission"].click()  # shows the page, changes no choice
    assert win.tabs.currentWidget() is win.commission and win.protocol_panel.name == chosen


# ----- defect 5: the link chosen in the window, errors naming its controls ------------------------
def test_the_serial_port_is_picked_on_the_device_panel(qtbot, window, monkeypatch):
    from labbench.gui import device_panel

    monkeypatch.setattr(device_panel, "serial_ports", lambda: [("/dev/ttyFAKE7", "Arduino Uno")])
    win = window()
    panel = win.device_panel
    assert "no rig file loaded" in panel.rig_label.text()  # not "<defaults>"
    assert not any("<defaults>" in t for t in win.log.texts())
    panel.backend.setCurrentText("serial")
    assert panel.link_title.text() == "port" and panel.port.isVisible()
    qtbot.waitUntil(lambda: panel.port.findText("/dev/ttyFAKE7") >= 0, timeout=10_000)
    panel.port.setCurrentText("")
    panel.connect_button.click()  # no port: the window says where to choose one
    assert win.banner.isVisible() and win.banner.text() == NO_PORT
    assert "[serial]" not in win.banner.text() and "port =" not in win.banner.text()
    assert win.state.link == "none"
    panel.port.setCurrentIndex(panel.port.findText("/dev/ttyFAKE7"))
    panel.connect_button.click()  # the port chosen is the one opened (it is not there)
    qtbot.waitUntil(lambda: win.state.link == "none" and "ttyFAKE7" in win.banner.text(),
                    timeout=30_000)
    assert "cannot open serial port /dev/ttyFAKE7" in win.banner.text()


def test_the_can_interface_is_picked_on_the_device_panel(qtbot, window, monkeypatch, tmp_path):
    from labbench.gui import device_panel

    monkeypatch.setattr(device_panel, "can_configs",
                        lambda: [{"interface": "virtual", "channel": "bench-bus"}])
    monkeypatch.delenv("CAN_INTERFACE", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path))  # no ~/.canrc
    win = window()
    panel = win.device_panel
    panel.backend.setCurrentText("canopen")
    assert panel.link_title.text() == "CAN bus"
    qtbot.waitUntil(lambda: panel.interface.findText("virtual: bench-bus (software bus, no adapter)") >= 0, timeout=10_000)
    assert panel.interface.currentText() == FROM_RIG
    panel.connect_button.click()  # none in the rig, none configured: the window's list named
    qtbot.waitUntil(lambda: win.banner.isVisible(), timeout=30_000)
    assert win.banner.text() == f"connect: {NO_CAN}" and "~/.canrc" not in win.banner.text()
    panel.interface.setCurrentIndex(panel.interface.findText("virtual: bench-bus (software bus, no adapter)"))
    assert panel.link_choice() == {"interface": "virtual", "channel": "bench-bus"}
    panel.connect_button.click()  # that bus is opened: no drive answers on it
    qtbot.waitUntil(lambda: win.state.link == "none" and "no CAN interface" not in win.banner.text()
                    and win.banner.isVisible(), timeout=60_000)


def test_a_rig_file_is_loaded_from_the_device_panel(qtbot, window, tmp_path):
    rig = tmp_path / "bench 4.toml"
    rig.write_text('[rig]\nname = "bench 4"\nforce_limit_n = 3.0\n')
    win = window()
    raised = _in_modal(qtbot, lambda d: (d.selectFile(str(rig)), d.accept()))
    win.device_panel.rig_button.click()
    assert not raised, raised
    assert win.rig.name == "bench 4" and str(rig) in win.device_panel.rig_label.text()
    assert str(rig) in win.commission.rig_label.text() and win.windowTitle() == "labbench: bench 4"


# ----- defect 6 (the window's side): simulators say so, one E-STOP wording, figures of one summary
@pytest.mark.parametrize("backend", ["sim", "sim-serial"])
def test_a_simulator_says_it_is_one_and_an_estop_reads_the_same(qtbot, window, backend):
    from labbench.device import ESTOP_STATE

    win = window()
    win.device_panel.backend.setCurrentText(backend)
    assert "no hardware" in win.device_panel.simulated.text()
    _connect(qtbot, win)
    name = win.device_panel.name_label.text()
    assert "simulated" in name and ("lock-step" in name or "paced" in name)
    qtbot.waitUntil(lambda: win.device_panel.health["state"].text() not in ("-", ""), timeout=5_000)
    if backend == "sim-serial":  # its link's counters as words, from the connection: all 0
        qtbot.waitUntil(lambda: win.device_panel.health["link"].text() != "-", timeout=5_000)
        link = win.device_panel.health["link"].text()
        assert link == "all zero" or ("{" not in link and all(
            part.split()[-1] == "0" for part in link.split(", "))), link
    _run(qtbot, win, "chirp-id", f0_hz=1.0, duration_s=2.0)
    rate = win.loop_status.labels["loop rate"].text()
    if "lock-step" in name:  # as fast as the host goes: no loop rate, no overruns to count
        assert "lock-step (unpaced)" in rate and "Hz" not in rate.split(":", 1)[1].replace("real time", "")
        assert "unpaced" in win.loop_status.labels["overruns"].text()
    win.activateWindow()
    qtbot.keyClick(win, QtCore.Qt.Key.Key_Escape)
    qtbot.waitUntil(lambda: win.device_panel.health["state"].text() == ESTOP_STATE, timeout=10_000)
    assert "LATCHED" in win.estop.text()


# ----- defect 10: a fixed layout ------------------------------------------------------------------
def _where(widget, win):
    return widget.mapTo(win, QtCore.QPoint(0, 0))


def test_nothing_moves_start_the_tabs_or_the_plots(qtbot, window):
    win = window()
    start, tabs, plots = (win.protocol_panel.start_button, win.tabs, win.live.splitter)
    qtbot.waitUntil(lambda: start.isVisible(), timeout=5_000)
    places = []

    def look(what):
        QtWidgets.QApplication.processEvents()
        places.append((what, _where(start, win), _where(tabs, win), _where(plots, win)))

    look("idle")
    for backend in ("serial", "canopen", "sim-serial", "sim"):
        win.device_panel.backend.setCurrentText(backend)
        look(f"backend {backend}")
    win.protocol_panel.choice.setCurrentText("etfe")
    win.protocol_panel.set_value("K", 5000.0)  # the pre-check grows a line ...
    win.protocol_panel.start_button.click()  # ... and a refusal shows the red banner
    assert win.banner.isVisible()
    look("refused, banner")
    win.protocol_panel.set_value("K", 50.0)
    win.protocol_panel.set_value("duration_s", 2.0)
    _connect(qtbot, win)
    look("connected")
    _run(qtbot, win, "etfe", duration_s=2.0)
    look("after a run, verdicts shown")
    win.activateWindow()
    qtbot.keyClick(win, QtCore.Qt.Key.Key_Escape)
    look("latched")
    first = places[0][1:]
    assert all(p[1:] == first for p in places), places


def test_long_lines_keep_their_room_and_say_all_in_their_tooltip(qtbot, window):
    win = window()
    line = ("run failed at 1 %: tripped: energy observer: 0.1514 J generated in 12 ms, more than "
            "the 0.05 J the rig allows; the force was zeroed and the device disabled")
    win.protocol_panel.set_progress(0.01, line)
    label = win.protocol_panel.time_left
    assert label.toolTip() == line and label.wordWrap()
    needed = label.fontMetrics().boundingRect(label.contentsRect(),
                                              int(QtCore.Qt.TextFlag.TextWordWrap), line)
    assert needed.height() <= label.contentsRect().height()  # its three lines hold it here


def test_the_write_hint_matches_the_write_button_without_a_rig_file(qtbot, window):
    win = window()
    win.tabs.setCurrentWidget(win.commission)
    win.commission.run_button.click()
    qtbot.waitUntil(lambda: win.mode == "idle" and win.last_run is not None, timeout=RUN_MS)
    assert not win.commission.write_button.isEnabled()
    text = win.commission.changes.text()
    assert "Write stamps" not in text and "no rig file loaded" in text
    assert "Rig file..." in win.commission.write_button.toolTip()


def test_display_units_apply_to_verdict_texts_too(qtbot, window):
    import re

    from labbench.readout.units import DisplayUnits

    win = window()
    _run(qtbot, win, "etfe", duration_s=4.0)
    text = win.live.verdicts.text()
    band = re.search(r"ETFE: \w+ over ([0-9.\u2013-]+) (rad/s|Hz)", text)
    assert band and band.group(2) == "rad/s", text
    assert "renders K = " in text  # the readout's sentence: what the display rendered
    win.units_choice.set_units(DisplayUnits("m", "rad", "Hz"))
    again = win.live.verdicts.text()
    band_hz = re.search(r"ETFE: \w+ over ([0-9.\u2013-]+) (rad/s|Hz)", again)
    assert band_hz and band_hz.group(2) == "Hz", again
    assert again.split("renders K", 1)[1].split(";")[0].endswith(" Hz")  # the sentence's band too


# ----- defect 1: tabs only show ---------------------------------------------------------------
def test_looking_at_every_tab_never_changes_what_start_runs(qtbot, window):
    win = window()
    win.protocol_panel.choice.setCurrentText("etfe")
    win.protocol_panel.set_value("duration_s", 2.0)
    bar = win.tabs.tabBar()
    for i in [*range(win.tabs.count()), 0]:  # every page clicked, then Live again
        qtbot.mouseClick(bar, QtCore.Qt.MouseButton.LeftButton, pos=bar.tabRect(i).center())
        assert win.tabs.currentIndex() == i and win.protocol_panel.name == "etfe"
    path = _run(qtbot, win, "etfe")
    assert "_etfe_" in path and win.last_run.results.get("etfe")
    # the Commissioning page runs its own protocol: the panel keeps its choice after it too
    win.tabs.setCurrentWidget(win.commission)
    win.commission.run_button.click()
    qtbot.waitUntil(lambda: win.mode == "idle" and "_commission_" in (win.session_path or ""),
                    timeout=RUN_MS)
    assert win.protocol_panel.name == "etfe"
    win.tabs.setCurrentWidget(win.live)
    assert "_etfe_" in _run(qtbot, win, "etfe")
