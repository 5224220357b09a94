"""Test modules that need what a platform lacks: not collected there, and said so.

Their subjects are covered on the platforms that have the ability; the code's behaviour
without it is what ``test_platform_posixless.py`` checks, everywhere.
"""
from __future__ import annotations

import sys

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
}

_skipped = {**LINUX_ONLY, **POSIX_ONLY} if sys.platform == "win32" else (
    LINUX_ONLY if not sys.platform.startswith("linux") else {})
collect_ignore = list(_skipped)


def pytest_report_header(config):
    return [f"not collected on {sys.platform}: {name} ({why})" for name, why in _skipped.items()]
