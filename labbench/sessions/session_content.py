"""What a session says: its whole stream joined, its VE, its analysis arrays and metadata."""
from __future__ import annotations

import math

import numpy as np

from labbench.model import device_delay
from labbench.model import device_friction
from labbench import records
from labbench.errors import UserError
from labbench.sessions.session_format import SessionReader, read_session
from labbench.model.ve import VirtualEnvironment


def session_ve(start: dict) -> VirtualEnvironment | None:
    """The VE a run started with, from its start record.

    Accepts a VE dict (``VirtualEnvironment.as_dict``) under ``start["ve"]`` or the
    protocol's ``ve``, or a protocol config with ``ve`` = kind and ``K``, ``B``,
    ``w0_rad_s``, ``td_s``. ``None`` when the record names no VE, or names one with values
    that are not numbers (a file's content is not trusted).
    """
    proto = start.get("protocol") if isinstance(start.get("protocol"), dict) else {}
    for candidate in (start.get("ve"), proto.get("ve")):
        if isinstance(candidate, dict):
            return VirtualEnvironment.from_dict(candidate)
    if not isinstance(proto.get("ve"), str):
        return None
    rig = start.get("rig") if isinstance(start.get("rig"), dict) else {}
    w0 = _number(proto, "w0_rad_s", None)
    return VirtualEnvironment(
        proto["ve"], K=_number(proto, "K", 0.0), B=_number(proto, "B", 0.0),
        w0=math.inf if w0 is None else w0,
        T=_number(proto, "sample_time_s", None) or _number(rig, "sample_time_s", None, "rig") or 0.001,
        td=_number(proto, "td_s", 0.0))


def _number(d: dict, key: str, default, where: str = "protocol"):
    """``d[key]`` as a float (``default`` when absent or null); a UserError naming the field
    when a start record holds something else there."""
    value = d.get(key)
    if value is None:
        return default
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise UserError(f"the start record's {where}.{key} is {type(value).__name__} "
                        f"{str(value)[:40]!r}, not a number")
    return float(value)


def ends_early(path, problem: str) -> str:
    """The one line every reader says of a session read up to a damaged record or one
    labbench would not have written (``SessionReader.problem``)."""
    return f"{path}: stream ends early: {problem}; the records before it are used"


def load_session(path, warn=None, need_start: bool = False) -> tuple[
        dict, dict, dict[str, np.ndarray], list[dict], dict | None, str | None]:
    """(start, descriptor, channels, events, stop, problem) of a session, pages joined;
    ``warn(line)`` hears ``ends_early`` when the stream ends early. ``need_start``: a session
    without a readable start record is one UserError saying why (nothing to export)."""
    reader = read_session(path)
    got = records.StreamCollector()
    with reader:
        records.fan_out(reader, [got])
    if need_start and not got.start:
        raise UserError(f"session {path} has no readable start record"
                        + (f" (stream ends early: {reader.problem})" if reader.problem else ""))
    if reader.problem and warn is not None:
        warn(ends_early(path, reader.problem))
    return (got.start, got.descriptor, records.concat_pages(got.pages), got.events, got.stop,
            reader.problem)


def analysis_meta(start: dict, desc: dict) -> dict:
    """Metadata keys of the analysis format (docs/analysis.md): fs, ve, K, B, w0, td,
    force_hold (the device's, when the session records it), device_delay_s (the device's
    own delay the run used, ``labbench.model.device_delay``, when not 0), coulomb_n with its interval,
    source and origin (the friction the run used, ``labbench.model.device_friction``, when it knew
    one), protocol."""
    rig = start.get("rig") if isinstance(start.get("rig"), dict) else {}
    device = start.get("device") if isinstance(start.get("device"), dict) else {}
    T = desc.get("sample_time_s") or rig.get("sample_time_s")
    ve = session_ve(start)
    meta = {"protocol": records.protocol_name(start)}
    if T:
        meta["fs"] = 1.0 / float(T)
    if ve is not None:
        meta.update(ve=ve.kind, K=ve.K, B=ve.B, td=ve.td)
        if math.isfinite(ve.w0):
            meta["w0"] = ve.w0
    for key in ("uid", "seed"):
        if start.get(key) is not None:
            meta[key] = start[key]
    if rig.get("name"):
        meta["rig"] = rig["name"]
    if device.get("force_hold"):
        meta["force_hold"] = device["force_hold"]
    delay = device_delay.from_start(start)
    if delay.s:
        meta[device_delay.META_KEY] = delay.s
    meta.update(device_friction.from_start(start).as_meta())
    return meta


def load_analysis_arrays(path, warn=None) -> dict:
    """``dict(t, force, position, meta)`` for the analysis.

    ``force`` is the exogenous force (the "excitation" channel), ``position`` the
    sampled position; ``meta`` has fs, ve, K, B, w0, td, protocol (docs/analysis.md).
    ``warn``: as ``load_session``'s.
    """
    start, desc, ch, _events, _stop, problem = load_session(path)
    if ch["t"].size == 0:  # the one line says why, when the stream ended early
        raise UserError(f"session {path} holds no samples"
                        + (f" (stream ends early: {problem})" if problem else ""))
    if problem and warn is not None:
        warn(ends_early(path, problem))
    return {
        "t": ch["t"].astype(float),
        "force": ch["excitation"].astype(float),
        "position": ch["position"].astype(float),
        "meta": analysis_meta(start, desc),
    }


def readout_of(path):
    """The readout (``labbench.readout.wording.Readout``) of a recorded session: its stop
    record's results with its start record
    (headers only; the sample pages are not decoded)."""
    from labbench.readout import wording

    got = records.StreamCollector()
    with SessionReader(path, decode_pages=False) as reader:
        records.fan_out(reader, [got])
    stop = got.stop if isinstance(got.stop, dict) else {}
    return wording.of_results(records.protocol_name(got.start) or "", stop.get("results"), got.start)
