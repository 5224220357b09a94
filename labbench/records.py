"""The one stream of records a run produces.

Recorder, live plots, analysis and replay all consume the same sequence:
``start`` -> ``descriptor`` -> any number of ``page`` and ``event`` -> ``stop``.
A record is a plain dict with a ``kind`` key (JSON-friendly apart from the numpy
arrays inside a page), so a session file read back is the same stream again.
"""
from __future__ import annotations

import time
import uuid
from typing import Callable, Iterable

import numpy as np

import labbench

START, DESCRIPTOR, PAGE, EVENT, STOP = "start", "descriptor", "page", "event", "stop"
KINDS = (START, DESCRIPTOR, PAGE, EVENT, STOP)

# Channels of a page: name -> unit. Every page holds equal-length arrays of all of them.
CHANNELS = {
    "t": "s",  # device time of the sample
    "seq": "1",  # device sequence number
    "position": "m",  # sampled position x[k]
    "velocity": "m/s",  # filtered velocity estimate v[k]
    "ve_force": "N",  # VE force computed at step k (before delay)
    "excitation": "N",  # exogenous force applied during step k
    "command": "N",  # force commanded for step k (after safety and delay)
    "flags": "1",  # safety / device bits (labbench.loop.chain documents them)
}

# What each channel is, in words (exports carry it beside the unit).
DESCRIPTIONS = {
    "t": "device time of the sample",
    "seq": "device sequence number (a gap is a dropped sample)",
    "position": "sampled position x[k]",
    "velocity": "filtered velocity estimate v[k] of the VE",
    "ve_force": "virtual-environment force computed at step k, before the delay",
    "excitation": "exogenous force applied during step k",
    "command": "force commanded for step k, after the safety envelope and the delay",
    "flags": "safety and device bits (labbench.loop.chain)",
}

Consumer = Callable[[dict], None]


def start_record(rig: dict, protocol: dict, seed: int | None, **extra) -> dict:
    return {
        "kind": START,
        "uid": uuid.uuid4().hex,
        "time": time.time(),
        "software": f"labbench {labbench.__version__}",
        "rig": rig,
        "protocol": protocol,
        "seed": seed,
        **extra,
    }


def descriptor_record(sample_time_s: float) -> dict:
    return {"kind": DESCRIPTOR, "channels": dict(CHANNELS), "sample_time_s": sample_time_s}


def page_record(index: int, data: dict[str, np.ndarray]) -> dict:
    missing = set(CHANNELS) - set(data)
    if missing:
        raise ValueError(f"page lacks channels {sorted(missing)}")
    return {"kind": PAGE, "index": index, "data": data}


def event_record(t_s: float, name: str, reason: str, **extra) -> dict:
    return {"kind": EVENT, "t": t_s, "name": name, "reason": reason, **extra}


STATUSES = ("success", "aborted", "failed")  # a stop record's status
CAUSES = ("device", "safety", "recording", "analysis", "error")  # a failed run's cause


def stop_record(status: str, reason: str = "", **extra) -> dict:
    """``status``: "success", "aborted" or "failed"; a failed run's ``cause`` (in ``extra``)
    says whose: "device" (a fault), "safety" (a trip), "recording" (the session could not
    be written), "analysis" (recorded whole, its analysis failed) or "error"."""
    return {"kind": STOP, "status": status, "reason": reason, "time": time.time(), **extra}


def protocol_name(start: dict) -> str:
    """The protocol a start record names, as text ("run" when it names none)."""
    proto = start.get("protocol")
    if isinstance(proto, dict):  # {"name": ...} or a protocol's describe(): {"protocol": ...}
        return str(proto.get("name") or proto.get("protocol") or "run")
    return str(proto or "run")


class RecordRouter:
    """Base class of a consumer: a record goes to ``on_<kind>``; the base's handlers ignore
    it, so a subclass overrides only the kinds it needs (an unknown kind is ignored)."""

    def __call__(self, rec: dict) -> None:
        handler = _HANDLERS.get(rec.get("kind"))
        if handler is not None:
            getattr(self, handler)(rec)

    def on_start(self, rec: dict) -> None:
        pass

    def on_descriptor(self, rec: dict) -> None:
        pass

    def on_page(self, rec: dict) -> None:
        pass

    def on_event(self, rec: dict) -> None:
        pass

    def on_stop(self, rec: dict) -> None:
        pass


_HANDLERS = {kind: f"on_{kind}" for kind in KINDS}


class StreamCollector(RecordRouter):
    """Keeps a whole stream: its (first) start, descriptor, pages, events and stop."""

    def __init__(self):
        self.start: dict = {}
        self.descriptor: dict = {}
        self.pages: list[dict] = []
        self.events: list[dict] = []
        self.stop: dict | None = None

    def on_start(self, rec: dict) -> None:
        self.start = self.start or rec

    def on_descriptor(self, rec: dict) -> None:
        self.descriptor = rec

    def on_page(self, rec: dict) -> None:
        self.pages.append(rec)

    def on_event(self, rec: dict) -> None:
        self.events.append(rec)

    def on_stop(self, rec: dict) -> None:
        self.stop = rec


def iso_time(epoch: float) -> str:
    """A record's ``time`` (seconds since the epoch) as ISO 8601 local time with its UTC
    offset, e.g. ``2026-11-26T11:33:29+01:00``."""
    from datetime import datetime

    return datetime.fromtimestamp(epoch).astimezone().isoformat(timespec="seconds")


def fan_out(records: Iterable[dict], consumers: Iterable[Consumer]) -> None:
    """Feed a stream to every consumer in order (replay uses this too)."""
    consumers = list(consumers)
    for rec in records:
        for c in consumers:
            c(rec)


def concat_pages(records: Iterable[dict]) -> dict[str, np.ndarray]:
    """All page data of a stream joined per channel."""
    parts: dict[str, list[np.ndarray]] = {name: [] for name in CHANNELS}
    for rec in records:
        if rec["kind"] == PAGE:
            for name in CHANNELS:
                parts[name].append(np.asarray(rec["data"][name]))
    return {
        name: (np.concatenate(p) if p else np.zeros(0)) for name, p in parts.items()
    }
