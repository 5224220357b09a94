"""Replay a recorded session as the live stream it was, and condense a stream."""
from __future__ import annotations

import math
import threading
import time

import numpy as np

from labbench import records
from labbench.errors import UserError
from labbench.sessions.session_format import SessionReader, read_session


# A recorded pause longer than this (or a wild time stamp) is replayed as this long.
MAX_GAP_S = 5.0
SPEED_RANGE = (1e-3, 1e6)


def replay(path, consumers, speed: float | None = None, stop: threading.Event | None = None,
           clock=time.monotonic, sleep=time.sleep) -> SessionReader:
    """Feed a session's stream to ``consumers`` (``records.fan_out``), as recorded.

    ``speed`` None: as fast as possible; otherwise a page is delivered when its last
    sample falls due at ``speed`` times real time (an event at its ``t``); a step
    back in time counts as none, a step forward as at most ``MAX_GAP_S``, so no
    time stamp in the file can stall the replay. Setting ``stop`` ends the replay
    early. Returns the reader (its ``problem`` tells of a damaged tail).
    """
    lo, hi = SPEED_RANGE
    if speed is not None and not lo <= speed <= hi:
        raise UserError(f"replay speed must be within [{lo:g}, {hi:g}] x real time, got {speed}")
    reader = read_session(path)

    def paced():
        t_prev, wall0, elapsed = None, None, 0.0
        for rec in reader:
            if stop is not None and stop.is_set():
                break
            t = _stream_time(rec)
            if speed is not None and t is not None and math.isfinite(t):
                if t_prev is None:
                    wall0 = clock()
                else:
                    elapsed += min(max(t - t_prev, 0.0), MAX_GAP_S)
                t_prev = t
                delay = wall0 + elapsed / speed - clock()
                if delay > 0 and stop is None:
                    sleep(delay)
                elif delay > 0 and stop.wait(delay):
                    break
            yield rec

    with reader:
        records.fan_out(paced(), consumers)
    return reader


def _stream_time(rec: dict) -> float | None:
    if rec.get("kind") == records.PAGE and len(rec["data"]["t"]):
        return float(rec["data"]["t"][-1])
    if rec.get("kind") == records.EVENT and rec.get("t") is not None:
        return float(rec["t"])
    return None


class StreamSummary(records.RecordRouter):
    """Consumer that condenses a stream: identity, samples, drops, events, status, timing."""

    def __init__(self):
        self.start: dict = {}
        self.stop: dict | None = None
        self.events: list[dict] = []
        self.n_records = self.n_pages = self.n_samples = self.dropped = 0
        self.t_first = self.t_last = None
        self.max_abs_command_n = 0.0
        self._last_seq = None

    def __call__(self, rec: dict) -> None:
        self.n_records += 1
        super().__call__(rec)

    def on_start(self, rec: dict) -> None:
        self.start = rec

    def on_page(self, rec: dict) -> None:
        d = rec["data"]
        n = len(d["t"])
        if n == 0:
            return
        self.n_pages += 1
        self.n_samples += n
        seq = np.asarray(d["seq"], dtype=np.int64)
        prev = self._last_seq if self._last_seq is not None else seq[0] - 1
        steps = np.diff(np.concatenate([[prev], seq]))
        self.dropped += int(np.sum(np.clip(steps - 1, 0, None)))
        self._last_seq = int(seq[-1])
        self.t_first = float(d["t"][0]) if self.t_first is None else self.t_first
        self.t_last = float(d["t"][-1])
        self.max_abs_command_n = max(self.max_abs_command_n, float(np.max(np.abs(d["command"]))))

    def on_event(self, rec: dict) -> None:
        self.events.append(rec)

    def on_stop(self, rec: dict) -> None:
        self.stop = rec

    def as_dict(self) -> dict:
        rig = self.start.get("rig") if isinstance(self.start.get("rig"), dict) else {}
        stop = self.stop or {}
        return {
            "uid": self.start.get("uid"),
            "protocol": records.protocol_name(self.start) if self.start else None,
            "rig": rig.get("name"),
            "status": stop.get("status", "incomplete"),
            "reason": stop.get("reason", ""),
            "records": self.n_records,
            "pages": self.n_pages,
            "samples": self.n_samples,
            "dropped_samples": self.dropped,
            "duration_s": (self.t_last - self.t_first) if self.n_samples else 0.0,
            "max_abs_command_n": self.max_abs_command_n,
            "events": [{"t": e.get("t"), "name": e.get("name"), "reason": e.get("reason")}
                       for e in self.events],
            "timing": stop.get("timing"),
        }
