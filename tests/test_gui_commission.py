"""The commissioning page driven as a technician drives it (issue 20): a rig file whose
``[sim]`` truth lies is named with its correction, the correction is written into the file
(comments kept, the old file backed up), a true rig passes with nothing to change; and the
window renders no spring on real hardware until the rig has passed its direction check,
refusing with the CLI's own line."""
import os

os.environ["QT_QPA_PLATFORM"] = "offscreen"  # before any Qt import

import functools  # noqa: E402
import re  # noqa: E402

import pytest  # noqa: E402

from labbench.commissioning import CLI_REMEDY  # noqa: E402
from labbench.errors import UserError  # noqa: E402
from labbench.gui.main_window import GATE_REMEDY  # noqa: E402
from labbench.gui.main_window import MainWindow  # noqa: E402
from labbench.registry import open_device  # noqa: E402
from labbench.rig import Rig, load_rig  # noqa: E402

RUN_MS = 120_000
T = Rig().sample_time_s
RIG_FILE = """# bench 3: the one by the window (this comment stays)
[rig]
name = "bench 3"   # as on its label
{rig}
[sim]
{sim}
"""
# the page's rows, as it titles them
DIRECTION, DELAY, SCALE, FRICTION, KMAX = ("1. direction", "2. delay", "3. scale",
                                           "4. friction and offset", "5. stiffest safe spring K_max")


def _window(qtbot, tmp_path, sim: str = "", rig: str = "", **options):
    path = tmp_path / "bench3.toml"
    path.write_text(RIG_FILE.format(sim=sim, rig=rig))
    win = MainWindow(load_rig(path), tmp_path / "sessions", realtime=False, **options)
    qtbot.addWidget(win)
    win.show()
    return win, path


def _commission(qtbot, win) -> dict[str, list[str]]:
    """Run commissioning from its page as a person does; the rows it then shows."""
    page = win.commission
    chosen = win.protocol_panel.choice.currentText()
    win.tabs.setCurrentWidget(page)  # looking at the page changes no choice
    assert win.protocol_panel.choice.currentText() == chosen
    win.last_run = None
    page.run_button.click()
    assert not page.run_button.isEnabled() and not page.write_button.isEnabled()
    qtbot.waitUntil(lambda: win.mode == "idle" and win.last_run is not None, timeout=RUN_MS)
    assert win.last_run.status == "success", win.last_run.reason
    assert win.tabs.currentWidget() is page and page.run_button.isEnabled()
    assert win.protocol_panel.choice.currentText() == chosen  # Start still runs what it did
    rows = page.check_rows()
    assert list(rows) == [DIRECTION, DELAY, SCALE, FRICTION, KMAX]
    return rows


def _levels(rows) -> dict[str, str]:
    return {check: cells[0] for check, cells in rows.items()}


def _write(win, path):
    """Press Write; (the file's text, its backup's text)."""
    page = win.commission
    assert page.write_button.isEnabled()
    page.write_button.click()
    assert not page.write_button.isEnabled()  # written: nothing left to write
    assert f"{path}: wrote " in page.written.text()
    return path.read_text(), path.with_name(path.name + ".bak").read_text()


def test_a_flipped_sign_is_named_written_and_then_passes(qtbot, tmp_path):
    win, path = _window(qtbot, tmp_path, sim="sign = -1")
    before = path.read_text()
    page = win.commission
    assert "not commissioned" in page.rig_label.text() and str(path) in page.rig_label.text()
    rows = _commission(qtbot, win)
    assert _levels(rows) == {DIRECTION: "failed", DELAY: "ok", SCALE: "ok", FRICTION: "ok", KMAX: "ok"}
    applied = int(re.fullmatch(r"0 of (\d+) pulses moved with the force", rows[DIRECTION][1]).group(1))
    assert applied >= 3  # of 4: the first starts at full force, before the enable gate opens
    assert "set [rig] position_sign = -1" in rows[DIRECTION][2]
    assert "N/m for a pure spring, B = 0" in rows[KMAX][1]  # the etfe pre-check's is at its B
    assert "commissioning: failed" in page.overall.text() and "direction" in page.overall.text()
    assert "position_sign = -1" in page.changes.text() and "direction_checked" not in page.changes.text()

    text, backup = _write(win, path)
    assert backup == before  # the old file, as it was
    assert "# bench 3: the one by the window (this comment stays)" in text and "# as on its label" in text
    assert load_rig(path).position_sign == -1 and not load_rig(path).direction_checked
    assert win.rig.position_sign == -1  # the window reads the file again ...
    assert win.device is None  # ... and opens the device with it at the next run
    assert "run commissioning again" in page.written.text()

    rows = _commission(qtbot, win)  # the handle now moves the way the file says
    assert set(_levels(rows).values()) == {"ok"}
    assert rows[DIRECTION][1] == f"{applied} of {applied} pulses moved with the force"
    assert "nothing to change" in page.changes.text() and "direction_checked" in page.changes.text()
    text, _ = _write(win, path)
    assert load_rig(path).direction_checked.endswith(win.session_path)
    assert "direction checked" in page.rig_label.text()
    assert "# as on its label" in text


def test_an_unstated_delay_is_measured_and_written(qtbot, tmp_path):
    win, path = _window(qtbot, tmp_path, sim="extra_delay_samples = 2")
    rows = _commission(qtbot, win)
    assert _levels(rows) == {DIRECTION: "ok", DELAY: "failed", SCALE: "ok", FRICTION: "ok", KMAX: "ok"}
    samples = float(rows[DELAY][1].split(" samples")[0])
    assert samples == pytest.approx(2.0, abs=0.1)  # issue 20: within 0.1 sample
    named = float(re.search(r"measured_td_s = ([0-9.e-]+)", rows[DELAY][2]).group(1))
    assert named == pytest.approx(2 * T, abs=0.1 * T)
    text, _ = _write(win, path)
    rig = load_rig(path)
    assert rig.measured_td_s == pytest.approx(named, abs=1e-8) and "commission" in rig.measured_td_from
    assert rig.direction_checked  # the direction passed in the same run: stamped
    assert "# as on its label" in text
    rows = _commission(qtbot, win)  # with the delay stated, nothing is left to change
    assert set(_levels(rows).values()) == {"ok"}
    assert float(rows[DELAY][1].split(" samples")[0]) == pytest.approx(2.0, abs=0.1)


def test_a_wrong_scale_is_named_not_written(qtbot, tmp_path):
    true_counts = Rig().counts_per_rev // 2  # the file says twice the encoder's counts
    win, path = _window(qtbot, tmp_path, sim=f"counts_per_rev = {true_counts}")
    rows = _commission(qtbot, win)
    assert _levels(rows)[SCALE] == "failed" and _levels(rows)[DIRECTION] == "ok"
    named = float(re.search(r"counts_per_rev = ([0-9.e+]+)", rows[SCALE][2]).group(1))
    assert named == pytest.approx(true_counts, rel=0.02)  # issue 20: scale within 2 %
    assert "nothing to change" in win.commission.changes.text()  # the mass cannot say which
    text, _ = _write(win, path)  # only the direction stamp
    assert "counts_per_rev" not in text.split("[sim]")[0]
    assert load_rig(path).direction_checked


def test_a_true_rig_passes_with_nothing_to_change(qtbot, tmp_path):
    win, path = _window(qtbot, tmp_path)
    rows = _commission(qtbot, win)
    assert set(_levels(rows).values()) == {"ok"}
    assert all(cells[2] == "nothing to change" for cells in rows.values())
    assert "commissioning: ok" in win.commission.overall.text()
    assert "rig changes: <b>nothing to change</b>" in win.commission.changes.text()
    before = load_rig(path)
    _write(win, path)
    after = load_rig(path)
    assert (after.position_sign, after.measured_td_s) == (before.position_sign, before.measured_td_s)
    assert after.direction_checked and not before.direction_checked


def test_the_built_in_rig_has_no_file_to_write(qtbot, tmp_path):
    win = MainWindow(Rig(), tmp_path / "sessions", realtime=False)
    qtbot.addWidget(win)
    win.show()
    _commission(qtbot, win)
    assert not win.commission.write_button.isEnabled()
    assert "no rig file" in win.commission.write_button.toolTip()


def _cli_refusal(rig) -> str:
    """The line ``labbench run etfe`` refuses the same spring with on real hardware (the
    runner's gate, as the CLI runs it)."""
    from labbench.registry import make_protocol
    from labbench.runner import run

    with pytest.raises(UserError) as refused:
        run(open_device("sim", rig), make_protocol("etfe", duration_s=2.0), [], rig=rig,
            simulated=False)
    return str(refused.value)


SIM_AS_HARDWARE = functools.partial(open_device, "sim")  # the simulator behind a real backend's name


def test_real_hardware_renders_no_spring_until_commissioned(qtbot, tmp_path):
    win, path = _window(qtbot, tmp_path)
    panel = win.protocol_panel
    panel.choice.setCurrentText("etfe")
    panel.set_value("duration_s", 2.0)
    assert "stable spring-damper" in panel.precheck.text()  # the simulator: no gate
    win.device_panel.backend.setCurrentText("canopen")  # real hardware, never commissioned
    line = _cli_refusal(win.rig)
    assert "labbench run commission" in line  # the command line names its command ...
    shown = line.replace(CLI_REMEDY, GATE_REMEDY)  # ... the window its own controls
    assert "Commissioning tab" in shown and "labbench run" not in shown
    assert shown in panel.precheck.text()

    panel.start_button.click()  # refused before the device is touched
    assert win.banner.isVisible() and win.banner.text() == shown
    assert win.mode == "idle" and win.device is None and not (tmp_path / "sessions").exists()

    # commissioning renders no VE: allowed on the same device; it passes and stamps the rig
    win.connect_device("canopen", opener=SIM_AS_HARDWARE)
    qtbot.waitUntil(lambda: win.device is not None, timeout=20_000)
    assert not win.simulated
    _commission(qtbot, win)
    _write(win, path)
    assert win.rig.direction_checked and "direction check" not in panel.precheck.text()

    # now the spring renders on it
    win.connect_device("canopen", opener=SIM_AS_HARDWARE)
    qtbot.waitUntil(lambda: win.device is not None, timeout=20_000)
    panel.choice.setCurrentText("etfe")
    win.last_run = None
    panel.start_button.click()
    qtbot.waitUntil(lambda: win.mode == "idle" and win.last_run is not None, timeout=RUN_MS)
    assert win.last_run.status == "success" and not win.banner.isVisible()


def test_skip_commissioning_renders_on_an_unchecked_rig(qtbot, tmp_path):
    win, _ = _window(qtbot, tmp_path, skip_commissioning=True)
    win.device_panel.backend.setCurrentText("canopen")
    win.connect_device("canopen", opener=SIM_AS_HARDWARE)
    qtbot.waitUntil(lambda: win.device is not None, timeout=20_000)
    win.protocol_panel.choice.setCurrentText("etfe")
    win.protocol_panel.set_value("duration_s", 2.0)
    win.protocol_panel.start_button.click()
    qtbot.waitUntil(lambda: win.mode == "idle" and win.last_run is not None, timeout=RUN_MS)
    assert win.last_run.status == "success"
