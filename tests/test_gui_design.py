"""The Design page (gui/design_view.py): what it shows is the design's own numbers for the
sliders' setting, it says when a setting is unstable or too noisy, it remembers its sliders,
and the window's page follows the rig."""
import os

os.environ["QT_QPA_PLATFORM"] = "offscreen"  # before any Qt import

import numpy as np  # noqa: E402
import pytest  # noqa: E402

from labbench.design.tradeoffs import Designer, Targets, device_for  # noqa: E402
from labbench.gui.design_view import SLIDERS, DesignView  # noqa: E402
from labbench.gui.main_window import MainWindow  # noqa: E402
from labbench.gui.settings import open_settings  # noqa: E402
from labbench.readout.numfmt import fmt  # noqa: E402
from labbench.rig import Rig, load_rig  # noqa: E402


def move(view, name, value):
    values = SLIDERS[name][2]
    view.sliders[name].setValue(int(np.argmin(np.abs(values - value))))


def test_every_move_shows_the_designs_numbers_for_the_sliders(qtbot):
    view = DesignView()
    qtbot.addWidget(view)
    for name, value in (("K", 200.0), ("B", 2.0), ("w0", 300.0), ("T", 0.5)):
        move(view, name, value)
        K, B, w0, T = (view.value(n) for n in ("K", "B", "w0", "T"))
        truth = Designer(device_for(Rig(), simulated=False)).evaluate(K, B, w0, T)
        assert view.point == truth
        text = view.numbers.text()
        assert f"{fmt(truth.k_max)} N/m" in text and f"{fmt(1e3 * truth.noise_command, 3)} mN" in text
        f, y = view.curves["command"].getOriginalDataset()
        assert len(f) > 100 and np.all(y > 0) and f[0] > 0  # drawn on log axes


def test_unstable_and_too_noisy_settings_say_so(qtbot):
    view = DesignView()
    qtbot.addWidget(view)
    move(view, "B", 0.0)
    move(view, "K", 1000.0)  # K_max 200 N/m without damping
    assert not view.point.stable and "UNSTABLE" in view.numbers.text()
    x, _ = view.curves["command"].getOriginalDataset()
    assert x is None or not len(x)  # no spectrum: no stationary noise
    move(view, "K", 50.0)
    move(view, "B", 2.0)
    move(view, "w0", 500.0)  # ~10 mN of command noise
    view.limit.setValue(2.0)
    assert view.point.stable and not view.point.within_limit
    assert "over the noise limit" in view.numbers.text()
    view.limit.setValue(0.0)  # none
    assert view.designer.targets == Targets() and view.point.within_limit


def test_sliders_are_remembered(qtbot, tmp_path):
    settings = open_settings(tmp_path / "s.ini")
    view = DesignView(settings=settings)
    qtbot.addWidget(view)
    move(view, "K", 300.0)
    move(view, "w0", 60.0)
    again = DesignView(settings=open_settings(tmp_path / "s.ini"))
    qtbot.addWidget(again)
    assert again.value("K") == pytest.approx(view.value("K"))
    assert again.value("w0") == pytest.approx(view.value("w0"))


def test_the_windows_page_follows_the_rig(qtbot, tmp_path):
    """A rough simulated rig (its [sim] quantises, adds 2 mN and rubs with 0.02 N): the page
    designs for that encoder step, amplifier noise and friction (its part of the noise
    shown), at the rig's 2 ms."""
    rig_file = tmp_path / "rough.toml"
    rig_file.write_text('[rig]\nname = "rough"\nsample_time_s = 0.002\n'
                        '[sim]\nquantize = true\nforce_noise_n = 0.002\ncoulomb_n = 0.02\n')
    win = MainWindow(load_rig(str(rig_file)), tmp_path / "sessions")
    qtbot.addWidget(win)
    titles = [win.tabs.tabText(i) for i in range(win.tabs.count())]
    assert "Design" in titles
    d = win.design.designer.device
    assert d.quantum_m == pytest.approx(Rig().metres_per_count) and d.force_noise_n == 0.002
    assert d.coulomb_n == 0.02 and "Coulomb friction 0.02 N" in win.design.device_line.text()
    assert win.design.value("T") == pytest.approx(0.002)
    friction_part = win.design.point.noise_friction
    assert friction_part > 0
    assert win.design.numbers.cells["noise_friction"].text() == f"{fmt(1e3 * friction_part, 3)} mN"
