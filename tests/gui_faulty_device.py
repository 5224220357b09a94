"""A device with a fault injected mid-run, for the GUI tests; Qt-free, because the GUI
opens it in its acquisition process (``labbench.gui.acquisition``), which must not import Qt."""
import time

from labbench.device import DeviceFault
from labbench.registry import open_device


class FaultyDevice:
    """The simulator, faulting after ``n_ok`` samples (a drive fault injected mid-run)."""

    def __init__(self, rig, n_ok):
        self.inner = open_device("sim", rig)
        self.n_ok = n_ok

    def _tick(self):
        self.n_ok -= 1
        if self.n_ok < 0:
            raise DeviceFault("injected: drive reported over-current")

    def read(self, timeout):
        self._tick()
        return self.inner.read(timeout)

    def read_raw(self, timeout):
        self._tick()
        return self.inner.read_raw(timeout)

    def __getattr__(self, name):
        return getattr(self.inner, name)


def open_faulty(rig, n_ok: int, **_options) -> FaultyDevice:
    """An opener for ``MainWindow.connect_device``: module-level, so it pickles."""
    return FaultyDevice(rig, n_ok)


class StallingDevice(FaultyDevice):
    """The simulator, paced, whose host stalls once: a sleep of ``stall_s`` before sample
    ``at`` (as a busy machine deschedules the acquisition process)."""

    def __init__(self, rig, at: int, stall_s: float):
        self.inner = open_device("sim", rig, realtime=True)
        self.at, self.stall_s = at, stall_s
        self.stalls = 0

    def _tick(self):
        self.at -= 1
        if self.at == 0:
            time.sleep(self.stall_s)
            self.stalls += 1


def open_stalling(rig, at: int, stall_s: float, **_options) -> StallingDevice:
    """An opener for ``MainWindow.connect_device`` (module-level: it pickles)."""
    return StallingDevice(rig, at, stall_s)


def wait_on(flag, ready, timeout_s: float = 60.0) -> None:
    """A process that says it is ready, then waits on ``flag`` (a SharedFlag) until killed."""
    ready.set()
    flag.wait(timeout_s)
