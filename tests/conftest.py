"""Test modules that need what a platform lacks: not collected there, and said so.

Their subjects are covered on the platforms that have the ability; the code's behaviour
without it is what ``test_platform_posixless.py`` checks, everywhere.
"""
from __future__ import annotations

import sys

import pytest

_FUZZ = "RLIMIT_AS (resource) and /proc bound each fuzz case's memory"
LINUX_ONLY = {
    "test_fuzz_cli.py": _FUZZ + "; a FIFO (os.mkfifo) is one of its inputs",
    "test_fuzz_inputs.py": _FUZZ,
    "test_fuzz_sessions.py": _FUZZ,
    "test_signals.py": "SIGHUP, and /proc/<pid>/status for the caught-signal mask",
    "test_realtime.py": "SCHED_FIFO, CPU affinity and the PM QoS latency file",
}
POSIX_ONLY = {
    "test_session_kill.py": "SIGKILL of a recording process at random moments",
    "test_device_death.py": "SIGKILL of the simulated drive's process",
}

# The firmware on the emulator needs Debian's AVR toolchain and simavr (`make avr-deps`,
# the CI workflow's apt step): Linux only. There a missing toolchain fails the tests that
# need it (the fixture below); elsewhere those tests are not collected.
AVR = "the AVR toolchain and simavr, Debian packages (make avr-deps)"
AVR_MODULES = ("test_avr_firmware.py", "test_avr_accuracy.py")
_LINUX = sys.platform.startswith("linux")

_skipped = {**LINUX_ONLY, **POSIX_ONLY} if sys.platform == "win32" else (
    LINUX_ONLY if not _LINUX else {})
if not _LINUX:
    _skipped.update(dict.fromkeys(AVR_MODULES, AVR))
collect_ignore = list(_skipped)


def pytest_report_header(config):
    lines = [f"not collected on {sys.platform}: {name} ({why})" for name, why in _skipped.items()]
    if not _LINUX:
        lines.append(f"not collected on {sys.platform}: the avr-sim cases of other modules ({AVR})")
    return lines


def pytest_collection_modifyitems(config, items):
    if not _LINUX:
        items[:] = [item for item in items if "avr" not in item.name]


@pytest.fixture
def avr_toolchain():
    """Fails (never skips) where the emulated board cannot be built: the project installs it."""
    from labbench.sim_backend.avr_build import problem

    if (why := problem()) is not None:
        pytest.fail(f"avr-sim cannot run here: {why}")


@pytest.fixture(autouse=True)
def _gui_thread_collection(request):
    """A test with windows collects Python's garbage as the application does: in the GUI
    thread only (labbench.gui.gc_policy); automatic collection comes back after it. Its
    screen has a desktop's room."""
    if "qtbot" not in request.fixturenames:
        yield
        return
    request.getfixturevalue("qapp")
    from PySide6 import QtCore, QtGui

    from labbench.gui.gc_policy import GuiThreadCollection

    # a desktop's screen: a first window is bounded by the screen's room (MainWindow), and
    # offscreen's screen is 800 x 800; a test of a smaller screen patches it again
    request.getfixturevalue("monkeypatch").setattr(
        QtGui.QScreen, "availableGeometry", lambda self: QtCore.QRect(0, 0, 1920, 1080))

    collection = GuiThreadCollection()
    yield
    collection.close()
