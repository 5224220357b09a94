"""labbench.platform: each ability the OS may lack degrades to one line; the Windows calls
are made as kernel32/winmm define them (checked against recording fakes here)."""
from __future__ import annotations

import ctypes
import signal
import threading

import pytest
import serial

from labbench import platform
from labbench.platform import latency, scheduling, signals
from labbench.platform.serial_peer import SocketTransport
from labbench.loop.realtime import RealtimeConfig, acquire


@pytest.fixture
def fresh(monkeypatch):
    """A process that has said nothing yet about missing abilities."""
    monkeypatch.setattr(platform, "_missing", set())


def test_a_missing_ability_is_one_line_once_per_process(fresh):
    lines = []
    for _ in range(3):
        platform.missing("a thing", "what follows", lines.append)
    platform.missing("another thing", "more", lines.append)
    assert len(lines) == 2 and all("\n" not in line for line in lines)
    assert lines[0].startswith("labbench: a thing not available on this platform (")
    assert lines[0].endswith("): what follows")


def test_without_sighup_or_sigbreak_the_other_signals_stay_and_one_line_says_so(fresh, monkeypatch,
                                                                                caplog):
    monkeypatch.delattr(signal, "SIGHUP")
    monkeypatch.delattr(signal, "SIGBREAK", raising=False)
    assert signals.ending_signals() == (signal.SIGINT, signal.SIGTERM)
    assert signals.ending_signals() == (signal.SIGINT, signal.SIGTERM)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and "SIGHUP" in said[0]


def test_a_console_close_delivers_the_signal_and_is_held_until_exit():
    delivered, exited = [], threading.Event()
    handler = signals.close_event_handler(lambda: delivered.append(1), exited, hold_s=30)
    assert handler(0) is False and handler(1) is False  # Ctrl-C, Ctrl-Break: the C runtime's
    assert delivered == []
    done = []
    t = threading.Thread(target=lambda: done.append(handler(signals.CTRL_CLOSE_EVENT)))
    t.start()
    t.join(0.2)
    assert delivered == [1] and t.is_alive()  # held: Windows would end the process on return
    exited.set()
    t.join(5)
    assert done == [True]


class FakeKernel32:
    """What the calls did, as kernel32 would answer (handles are tokens)."""

    def __init__(self, refuse=()):
        self.refuse, self.calls, self.handlers = set(refuse), [], []
        self.priority_class, self.thread_priority = 0x20, 0  # NORMAL, THREAD_PRIORITY_NORMAL

    def SetConsoleCtrlHandler(self, handler, add):
        self.calls.append(("SetConsoleCtrlHandler", add))
        (self.handlers.append if add else self.handlers.remove)(handler)
        return 1

    def GetCurrentProcess(self):
        return "process"

    def GetCurrentThread(self):
        return "thread"

    def GetPriorityClass(self, h):
        return self.priority_class

    def SetPriorityClass(self, h, value):
        if "SetPriorityClass" in self.refuse:
            return 0
        self.priority_class = value
        return 1

    def GetThreadPriority(self, h):
        return self.thread_priority

    def SetThreadPriority(self, h, value):
        if "SetThreadPriority" in self.refuse:
            return 0
        self.thread_priority = value
        return 1


def test_the_console_handler_is_registered_inside_the_block_only():
    k = FakeKernel32()
    with signals.console_close(kernel32=k):
        (callback,) = k.handlers
        assert callback(0) == 0  # a real ctypes callback: Ctrl-C passed on to the C runtime
    assert k.handlers == [] and k.calls == [("SetConsoleCtrlHandler", True),
                                            ("SetConsoleCtrlHandler", False)]


def test_windows_priority_high_class_and_time_critical_then_restored():
    k, undo, refused = FakeKernel32(), [], []
    assert scheduling.raise_windows_priority(undo, refused, kernel32=k)
    assert (k.priority_class, k.thread_priority) == (0x80, 15) and refused == []
    for u in reversed(undo):
        u()
    assert (k.priority_class, k.thread_priority) == (0x20, 0)


def test_windows_priority_refused_is_named_and_nothing_is_left_changed():
    k, undo, refused = FakeKernel32(refuse={"SetThreadPriority"}), [], []
    assert not scheduling.raise_windows_priority(undo, refused, kernel32=k)
    assert refused and "THREAD_PRIORITY_TIME_CRITICAL" in refused[0]
    for u in reversed(undo):
        u()
    assert k.priority_class == 0x20


def test_the_windows_latency_request_is_the_1_ms_timer_held_until_undone():
    class Winmm:
        periods: list = []

        def timeBeginPeriod(self, ms):
            self.periods.append(ms)
            return 0

        def timeEndPeriod(self, ms):
            self.periods.remove(ms)
            return 0

    w, undo = Winmm(), []
    assert latency.hold(0, undo, winmm=w) is None and w.periods == [1]
    undo.pop()()
    assert w.periods == []


def test_realtime_where_nothing_is_offered_is_one_line_per_ability_and_the_loop_goes_on(
        fresh, monkeypatch):
    """macOS, or a Linux Python without os.sched_*: scheduling and the latency request missing."""
    monkeypatch.setattr(scheduling, "kind", lambda: None)
    monkeypatch.setattr(latency, "kind", lambda: None)
    lines = []
    for _ in range(2):
        with acquire(RealtimeConfig(lock_memory=False), warn=lines.append) as grant:
            rec = grant.record
    assert rec["unavailable"] == ["real-time scheduling", "the CPU latency request"]
    assert rec["priority"] == 0 and rec["cpu_latency_us"] is None
    assert len(lines) == 2 and all("not available on this platform" in x for x in lines)


def test_the_socket_transport_carries_bytes_both_ways_and_its_close_fails_the_host():
    t = SocketTransport()
    host = serial.serial_for_url(t.url, timeout=1)
    try:
        t.write(b"board->host")
        assert host.read(11) == b"board->host"
        host.write(b"cmd")
        got = b""
        for _ in range(50):
            got += t.read(0.05)
            if len(got) == 3:
                break
        assert got == b"cmd"
        assert t.read(0.01) == b""  # nothing more: the timeout, not a block
        t.close()
        with pytest.raises(serial.SerialException):
            host.read(1)
    finally:
        host.close()
        t.close()
