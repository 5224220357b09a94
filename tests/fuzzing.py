"""The fuzz property and its harness, shared by tests/test_fuzz_*.py.

Property, for every case: the command ends with exit 0 and a result on stdout,
or exit 2 with exactly one ``...: error: ...`` line on stderr (``run`` may also
end with exit 1, a run whose status is "failed", with its result printed) -
never an uncaught exception, never past ``TIME_LIMIT_S``, never more than
``MEMORY_LIMIT`` bytes of address space beyond what the process held before
the case (RLIMIT_AS, lowered for the case: an allocation past it fails, and the
failure escapes as a traceback the property catches). The limits catch hangs
and blow-ups; they are not speed goals.

Cases run in-process (``labbench.cli.main``) so a few hundred fit in seconds;
``run_cli_isolated`` runs one in a child process under RLIMIT_AS and a wall-clock
timeout, for the slow suite and for cases too big to share a process.
"""
from __future__ import annotations

import contextlib
import io
import json
import os
import resource
import signal
import struct
import subprocess
import sys
import time
import traceback
import zlib
from dataclasses import dataclass
from pathlib import Path

import pytest

from labbench.cli import main
from labbench.sessions.session_format import MAGIC

TIME_LIMIT_S = 30.0  # per case: hang detector, generous for a loaded shared machine
MEMORY_LIMIT = 1 << 30  # address space a case may add
ISOLATED_MEMORY = 2 << 30  # RLIMIT_AS of an isolated case (the interpreter and numpy included)

HOSTILE_NUMBERS = ["1e308", "-1e308", "1e-320", "-1e-320", "nan", "inf", "-inf", "0", "-0",
                   "-1", "1e30", "9" * 400, "0x10", "1_000", "", " ", "abc", "$x$", "1,2",
                   "\n", "\x00"]


class CaseTimeout(BaseException):
    """Raised by SIGALRM inside a case that ran past TIME_LIMIT_S."""


@dataclass
class Outcome:
    argv: list
    code: int | None
    out: str
    err: str
    seconds: float
    crash: str | None  # the traceback of an exception that escaped main()


def _alarm(_signum, _frame):
    raise CaseTimeout


def _address_space() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[0]) * resource.getpagesize()


def run_cli(argv: list[str], time_limit_s: float = TIME_LIMIT_S,
            memory: int = MEMORY_LIMIT) -> Outcome:
    """``labbench <argv>`` in this process, stdout/stderr captured, time and memory bounded.
    The tests run it from a scratch working directory (the ``scratch_cwd`` fixture), so a
    relative or empty output name never lands in the source tree."""
    argv = [str(a) for a in argv]
    out, err = io.StringIO(), io.StringIO()
    code, crash = None, None
    previous = signal.signal(signal.SIGALRM, _alarm)
    limit = resource.getrlimit(resource.RLIMIT_AS)
    t0 = time.monotonic()
    signal.setitimer(signal.ITIMER_REAL, time_limit_s)
    try:
        resource.setrlimit(resource.RLIMIT_AS, (_address_space() + memory, limit[1]))
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(argv)
    except SystemExit as exc:  # argparse
        code = exc.code if isinstance(exc.code, int) else 2
    except CaseTimeout:
        crash = f"ran past {time_limit_s:g} s"
    except BaseException:  # noqa: BLE001 - this is what the fuzzing looks for
        crash = traceback.format_exc()
    finally:
        resource.setrlimit(resource.RLIMIT_AS, limit)
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
        seconds = time.monotonic() - t0
    return Outcome(argv, code, out.getvalue(), err.getvalue(), seconds, crash)


def run_cli_isolated(argv: list[str], cwd: Path, time_limit_s: float = 120.0,
                     memory: int = ISOLATED_MEMORY) -> Outcome:
    """The same case in a child process under RLIMIT_AS and a wall-clock timeout."""
    def limits():
        resource.setrlimit(resource.RLIMIT_AS, (memory, memory))

    t0 = time.monotonic()
    try:
        p = subprocess.run([sys.executable, "-m", "labbench.cli", *map(str, argv)], cwd=cwd,
                           capture_output=True, text=True, timeout=time_limit_s,
                           preexec_fn=limits, env={**os.environ, "QT_QPA_PLATFORM": "offscreen"})
    except subprocess.TimeoutExpired:
        return Outcome(argv, None, "", "", time_limit_s, f"ran past {time_limit_s:g} s")
    crash = p.stderr if "Traceback" in p.stderr or p.returncode < 0 else None
    return Outcome(argv, p.returncode, p.stdout, p.stderr, time.monotonic() - t0, crash)


def problems(o: Outcome, allow_failed_run: bool = False) -> list[str]:
    """What breaks the property in one outcome (empty: it holds)."""
    bad = []
    if o.crash:
        return [f"{o.argv}: {o.crash.strip().splitlines()[-1][:300]}"]
    if "Traceback" in o.err:
        bad.append("traceback on stderr")
    lines = [x for x in o.err.strip().splitlines() if ": warning: " not in x]
    if o.code == 0:
        if not o.out.strip():
            bad.append("exit 0 without a result")
    elif o.code == 2:
        if len(lines) != 1 or ": error: " not in lines[0]:
            bad.append(f"exit 2 without one error line: {o.err[:300]!r}")
    elif o.code == 1 and allow_failed_run:
        if not o.out.strip():
            bad.append("exit 1 without the run's result")
    else:
        bad.append(f"exit {o.code}: {o.err[:300]!r}")
    return [f"{o.argv}: {b}" for b in bad]


class Tally:
    """Counts cases and outcomes per entry point (printed for the closing note)."""

    def __init__(self):
        self.rows: dict[str, list[int]] = {}
        self.failures: list[str] = []
        self.slowest = (0.0, None)

    def add(self, entry: str, o: Outcome, allow_failed_run: bool = False) -> None:
        row = self.rows.setdefault(entry, [0, 0, 0])  # cases, exit 0 (or 1), exit 2
        row[0] += 1
        row[1 if o.code in (0, 1) else 2] += 1
        self.failures += problems(o, allow_failed_run)
        self.slowest = max(self.slowest, (o.seconds, " ".join(map(str, o.argv))[:120]),
                           key=lambda x: x[0])

    def report(self) -> str:
        lines = [f"{entry:28s} {n:5d} cases: {ok:4d} results, {err:4d} one-line errors"
                 for entry, (n, ok, err) in self.rows.items()]
        lines.append(f"slowest case {self.slowest[0]:.2f} s ({self.slowest[1]})")
        return "\n".join(lines)


# ----- session files with valid checksums and hostile content ---------------------------------
def chunk(head, data: bytes, seq: int) -> bytes:
    """One session chunk around any JSON value and data part, checksum valid."""
    body = head if isinstance(head, bytes) else json.dumps(head).encode()
    prefix = struct.pack("<4sIIQ", b"REC:", len(body), len(data), seq)
    crc = zlib.crc32(data, zlib.crc32(body, zlib.crc32(prefix)))
    return prefix + struct.pack("<I", crc) + body + data


def write_chunks(path: Path, items) -> Path:
    """A session file of ``(json value, data bytes)`` items, numbered in order."""
    with open(path, "wb") as f:
        f.write(MAGIC)
        for seq, (head, data) in enumerate(items):
            f.write(chunk(head, data, seq))
    return path


def items_of(stream) -> list[list]:
    """``[json value, data bytes]`` per record of a stream, as the writer encodes them."""
    from labbench.sessions.session_format import encode_record

    out = []
    for rec in stream:
        raw = encode_record(rec, 0)
        json_len = struct.unpack("<I", raw[4:8])[0]
        out.append([json.loads(raw[24:24 + json_len]), raw[24 + json_len:]])
    return out


@pytest.fixture(autouse=True)
def scratch_cwd(tmp_path, monkeypatch):
    """Each fuzz test runs in its own empty working directory (import it into the module)."""
    monkeypatch.chdir(tmp_path)
