"""One session as a report sees it: its records and channels, and facts derived from them."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from labbench.model.predictions import recorded_plant
from labbench.records import iso_time, protocol_name
from labbench.report import shapes
from labbench.sessions.session_content import load_session, session_ve
from labbench.model.ve import Plant, VirtualEnvironment


@dataclass
class ReportSession:
    path: Path
    start: dict
    desc: dict
    ch: dict
    events: list
    stop: dict | None
    problem: str | None
    index: int = 1  # its number in the report: "#1", "#2", ...
    malformed: tuple[str, ...] = ()  # fields left out: not the shape the report reads

    @property
    def tag(self) -> str:
        return f"#{self.index}"

    @property
    def protocol(self) -> str:
        return protocol_name(self.start)

    @property
    def config(self) -> dict:
        """The protocol's settings as recorded (``describe()`` less the name)."""
        proto = self.start.get("protocol")
        if not isinstance(proto, dict):
            return {}
        return {k: v for k, v in proto.items() if k not in ("protocol", "name")}

    @property
    def results(self) -> dict:
        return dict((self.stop or {}).get("results") or {})

    @property
    def status(self) -> str:
        return str((self.stop or {}).get("status", "incomplete"))

    @property
    def T(self) -> float:
        rig = self.start.get("rig") or {}
        return float(self.desc.get("sample_time_s") or rig.get("sample_time_s") or 0.001)

    @property
    def plant(self) -> Plant | None:
        """The device model the run assumed (results first: what analysis used)."""
        return recorded_plant(self.start, self.results)

    @property
    def ve(self) -> VirtualEnvironment | None:
        return session_ve(self.start)

    @property
    def rig_name(self) -> str:
        return str((self.start.get("rig") or {}).get("name") or "-")

    @property
    def device(self) -> str:
        return str((self.start.get("device") or {}).get("kind") or "-")

    @property
    def started(self) -> str:
        t = self.start.get("time")
        return iso_time(t) if t is not None else "-"

    @property
    def duration_s(self) -> float:
        t = self.ch["t"]
        return float(t[-1] - t[0]) if t.size else 0.0

    @property
    def dropped(self) -> int:
        seq = self.ch["seq"].astype(np.int64)
        return int(np.sum(np.clip(np.diff(seq) - 1, 0, None))) if seq.size > 1 else 0

    @property
    def trips(self) -> list[dict]:
        """Safety events (not the bookkeeping ones, nor the loop's timing: ``timing_flag``)."""
        from labbench.loop.timing import EVENTS

        return [e for e in self.events if e.get("name") not in ("segment", "enabled", *EVENTS)]

    @property
    def timing_problem(self) -> str | None:
        """What the live status bar showed of a paced loop that did not keep time: its
        overruns and worst stall (the stop record's timing); None when it kept time."""
        from labbench.loop.timing import summary

        timing = (self.stop or {}).get("timing") or {}
        if not (timing.get("paced") and timing.get("overruns")):
            return None
        return summary({k: v for k, v in timing.items() if k != "realtime"})


def load(path, index: int = 1, warn=None) -> ReportSession:
    """The session, its start and stop records conformed to what the report reads
    (``labbench.report.shapes``); ``warn``: as ``load_session``'s."""
    start, desc, ch, events, stop, problem = load_session(path, warn)
    malformed: list[str] = []
    start = shapes.conform(start, shapes.START, "start", malformed)
    if stop is not None:
        stop = shapes.conform(stop, shapes.STOP, "stop", malformed)
    return ReportSession(Path(path), start, desc, ch, events, stop, problem, index=index,
                         malformed=tuple(malformed))
