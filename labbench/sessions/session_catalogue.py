"""The session catalogue: what sessions a folder holds, from their headers alone."""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

from labbench import records
from labbench.errors import LabbenchError, UserError
from labbench.sessions.session_format import SessionReader, looks_like_session


@dataclass(frozen=True)
class SessionSummary:
    path: Path
    uid: str | None
    time: float | None
    rig_name: str | None
    protocol: str | None
    status: str  # the stop record's status, or "incomplete"
    n_samples: int
    # what tells runs of one protocol apart (the window's Sessions list): the VE rendered
    # ("none": open loop), its K [N/m] and B [N s/m], the record's length [s], and the
    # worst of the verdicts its results carry (ok, doubtful, failed; None: none recorded)
    ve: str | None = None
    K: float | None = None
    B: float | None = None
    duration_s: float | None = None
    verdict: str | None = None
    overruns: int = 0  # loop periods over 1.5 T of a paced run (its stop record's timing)
    device: str | None = None  # the backend it ran on ("sim", "avr-sim", "canopen (simulated)")
    # a stability probe's result as its readout words it: the variable, the measured boundary
    # ("200.0355 N/m (200.0345 to 200.0365)") and its agreement ("measured against exact",
    # "+0.0063 %"; the friction-aware one where it was judged); None: no boundary
    boundary: tuple[str, str, tuple[str, str] | None] | None = None


class _HeaderCollector(records.StreamCollector):
    """Start and stop records and the sample count of undecoded pages (shapes only)."""

    n_samples = 0

    def on_page(self, rec: dict) -> None:
        shapes = list(rec["data"].values())
        self.n_samples += int(shapes[0][0]) if shapes and shapes[0] else 0


def summarize(path) -> SessionSummary:
    """Header facts of one session without decoding its sample arrays. A session holding a
    record labbench would not have written is a UserError naming it (a torn tail, a run cut
    short, is a session: "incomplete")."""
    got = _HeaderCollector()
    with SessionReader(path, decode_pages=False) as reader:
        records.fan_out(reader, [got])
    if reader.not_as_written:
        raise UserError(f"stream ends early: {reader.problem}")
    start, stop, n = got.start, got.stop, got.n_samples
    rig = start.get("rig") if isinstance(start.get("rig"), dict) else {}
    try:
        from labbench.sessions.session_content import session_ve

        ve = session_ve(start) if start else None
    except (LabbenchError, TypeError, ValueError):
        ve = None  # a VE the record does not state readably: left blank
    T = _number(got.descriptor.get("sample_time_s")) or _number(rig.get("sample_time_s"))
    return SessionSummary(
        path=Path(path),
        uid=start.get("uid"),
        time=start.get("time"),
        rig_name=rig.get("name"),
        protocol=records.protocol_name(start) if start else None,
        status=str(stop.get("status")) if stop else "incomplete",
        n_samples=n,
        ve=ve.kind if ve is not None else None,
        K=ve.K if ve is not None and ve.kind != "none" else None,
        B=ve.B if ve is not None and ve.kind != "none" else None,
        duration_s=n * T if T else None,
        verdict=worst_level((stop or {}).get("results")),
        overruns=_overruns(stop),
        device=_device(start.get("device")),
        boundary=_boundary(records.protocol_name(start) if start else None,
                           (stop or {}).get("results")),
    )


def _boundary(protocol, results):
    """A stability probe's measured boundary and agreement as its readout words them
    (``labbench.readout.wording``; the friction-aware agreement before the exact one)."""
    from labbench.readout.wording import of_results

    if not isinstance(results, dict) or not isinstance(results.get("measured_boundary"), (int, float)):
        return None
    rows = dict(of_results(protocol or "", results).row_texts())
    var = results.get("variable")
    measured = rows.get(f"boundary ({var}), measured")
    if measured is None or var not in ("K", "td"):
        return None
    label = next((k for k in ("measured against friction-aware", "measured against exact")
                  if k in rows), None)
    return var, measured, (label, rows[label]) if label else None


def _device(d) -> str | None:
    """The backend a start record's device description names (a simulated peer of a real
    protocol says so: the simulated CANopen drive's kind is "canopen")."""
    kind = d.get("kind") if isinstance(d, dict) else None
    if not isinstance(kind, str) or not kind:
        return None
    simulated = d.get("simulated") is True and not kind.startswith(("sim", "avr-sim"))
    return kind + (" (simulated)" if simulated else "")


def _overruns(stop) -> int:
    """The overruns a paced run's stop record counts (0: none, unpaced, or not recorded)."""
    timing = stop.get("timing") if isinstance(stop, dict) else None
    n = timing.get("overruns") if isinstance(timing, dict) and timing.get("paced") is True else 0
    return n if isinstance(n, int) and not isinstance(n, bool) and n > 0 else 0


def _number(x) -> float | None:
    return float(x) if isinstance(x, (int, float)) and not isinstance(x, bool) and x > 0 else None


def worst_level(results) -> str | None:
    """The worst level of the verdicts a run's results carry: its own, each analysis's
    (``etfe``, ``loop_fit``, each check), each identification fit's; None when there are
    none (what is not a verdict is left out: recorded results are not trusted)."""
    from labbench.readout.verdict import from_dict, worst

    if not isinstance(results, dict):
        return None
    found = [from_dict(results.get("verdict"))]
    for value in results.values():
        if isinstance(value, dict):
            found.append(from_dict(value.get("verdict")))
            found += [from_dict(v.get("verdict")) for v in value.values() if isinstance(v, dict)]
    found = [v for v in found if v is not None]
    return worst(found).level if found else None


def list_sessions(directory, on_skip=None) -> list[SessionSummary]:
    """Every session file directly in ``directory``, oldest first.

    A file that cannot be read (no permission, hostile content that is not a
    session's) is skipped: ``on_skip(path, reason)`` is called, by default a
    ``warnings.warn``, so one bad file never stops the scan.
    """
    d = Path(directory)
    if not d.is_dir():
        raise UserError(f"not a directory: {d}")
    found = []
    for p in sorted(d.iterdir()):
        try:
            if not (p.is_file() and looks_like_session(p)):
                continue
            found.append(summarize(p))
        except (LabbenchError, OSError, ValueError, RecursionError, MemoryError) as exc:
            reason = str(exc) or type(exc).__name__
            if on_skip is None:
                warnings.warn(f"skipped {p}: {reason}", stacklevel=2)
            else:
                on_skip(p, reason)
    return sorted(found, key=lambda s: (s.time or 0.0, str(s.path)))


# protocols whose theory needs no plant identified beforehand: their own analysis is the
# identification (chirp-ID), or they check the rig's nominal model itself (commissioning)
OWN_PLANT = ("chirp-id", "commission")


def _newest_results(directory, rig_name: str, protocol: str, on_skip=None):
    """(results, path) of each successful ``protocol`` session of rig ``rig_name`` in
    ``directory``, newest first; the results as the stop record holds them ({} when it holds
    none). An unreadable stop record is passed over (``on_skip``)."""
    if not Path(directory).is_dir():
        return
    for s in reversed(list_sessions(directory, on_skip=on_skip)):
        if s.protocol != protocol or s.status != "success" or s.rig_name != rig_name:
            continue
        try:
            with SessionReader(s.path, decode_pages=False) as reader:
                stop = next((r for r in reader if r.get("kind") == records.STOP), {})
        except (LabbenchError, OSError, ValueError) as exc:
            if on_skip is not None:
                on_skip(s.path, str(exc) or type(exc).__name__)
            continue
        res = stop.get("results")
        yield (res if isinstance(res, dict) else {}), str(s.path)


def last_results(directory, rig_name: str, protocol: str, on_skip=None) -> tuple[dict, str] | None:
    """The results of the newest successful ``protocol`` session of rig ``rig_name`` in
    ``directory`` and its path (e.g. the rig's last commissioning); None when there is none."""
    return next(_newest_results(directory, rig_name, protocol, on_skip), None)


def last_identified(directory, rig_name: str, on_skip=None) -> dict | None:
    """The newest successful chirp-ID session of rig ``rig_name`` in ``directory`` as
    ``identified_plant`` reads it, or None (no folder, no such session). The plant a run uses
    when none is given (``labbench run --plant-from last-id``, the window, a campaign): what
    it was identified as, and where."""
    for res, path in _newest_results(directory, rig_name, "chirp-id", on_skip):
        found = identified_plant(res, path)
        if found is not None:
            return found
    return None


def identified_plant(res: dict, session) -> dict | None:
    """A chirp-ID's results as the plant runs take: ``{"m", "b", "session", "coulomb_n",
    "coulomb_ci95"}`` (its l2 fit's Coulomb term and its interval; None when the model had
    none); None when m, b are not a plant (not numbers within the physical range)."""
    from labbench.model import device_friction
    from labbench.model.ve import Plant

    try:
        plant = Plant(res.get("m"), res.get("b"))
    except (UserError, TypeError):
        return None
    ident = res.get("identification") or {}
    best = ident.get("l2") or next(iter(ident.values()), {}) if isinstance(ident, dict) else {}
    best = best if isinstance(best, dict) else {}
    ci = (best.get("ci95") or {}).get("coulomb") if isinstance(best.get("ci95"), dict) else None
    friction = device_friction.from_dict({"n": best.get("coulomb"), "ci95": ci, "origin": "given"})
    known = friction is not None and friction.known
    return {"m": plant.m, "b": plant.b, "session": session,
            "coulomb_n": friction.n if known else None,
            "coulomb_ci95": list(friction.ci95) if known and friction.ci95 is not None else None}


def plant_options(found: dict, fields) -> dict:
    """The protocol options a plant identified in a chirp-ID (``last_identified``) sets: m
    and b, and its Coulomb friction with its interval where the protocol has
    ``plant_coulomb_n`` among its ``fields`` (``labbench.model.device_friction``)."""
    out = {"plant_m_kg": found["m"], "plant_b": found["b"]}
    if "plant_coulomb_n" in fields and found.get("coulomb_n") is not None:
        out.update(plant_coulomb_n=found["coulomb_n"], plant_coulomb_ci95=found.get("coulomb_ci95"))
    return out
