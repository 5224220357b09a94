"""The device's own delay: one number, resolved once per run, read by every analysis.

What it is: the time from the host's command to the force the plant feels, on the
*whole* command (the VE's force and the excitation alike): amplifier and current loop,
transport, a drive that applies a synchronous RPDO's torque at the next SYNC (CiA 301
sec. 7.2.2: synchronous PDO data take effect at the next SYNC), a board's filter. It is
not the VE's own software delay ``td`` (a delay line on the VE force only, whole
samples, the paper's td): the two move the measured impedance differently
(``labbench.model.linear`` module doc: ``latency`` delays the excitation's path to the
plant as well, so F_exo/X gains a factor e^{jw latency} on the plant's term while
the VE's term sees T/2 + td + latency). A position measured late by whole samples
gives the same F_exo/X as a command applied late by as many, so one number covers both.

Seconds, fractions of a sample allowed (the exact sampled model splits the held
command over two samples, ``labbench.model.linear.latency_split``).

Where it comes from, first found wins (``resolve``):

1. ``given``: an explicit value (``--device-delay-s``, an API argument);
2. ``rig``: the rig file's ``[rig] measured_td_s`` (with ``measured_td_from``): a
   measurement of the whole device, so it includes anything the device declares;
3. ``device``: the backend's own declaration (``DeviceDescription.device_delay_s``,
   with ``device_delay_why``), e.g. the CANopen driver on a drive whose torque RPDO is
   synchronous;
4. ``none``: 0 s.

A run's start record carries ``device_delay = {"s", "source", "origin"}`` and the
analysis metadata ``device_delay_s``; sessions written before this model carried the
rig's value as ``precheck.measured_td.td_s`` and ``td_measured``, read here too.
"""
from __future__ import annotations

from dataclasses import dataclass

from labbench.errors import UserError
from labbench.scales import is_number

ORIGINS = ("given", "rig", "device", "none")
MAX_DELAY_S = 1.0  # as the rig file's bound: no haptic loop survives a longer one
META_KEY = "device_delay_s"
_OLD_META_KEY = "td_measured"


@dataclass(frozen=True)
class DeviceDelay:
    s: float = 0.0
    source: str = ("none known: the VE's td only (labbench run commission or analyze etfe "
                   "--fit measures it; store it as [rig] measured_td_s)")
    origin: str = "none"

    def as_dict(self) -> dict:
        return {"s": self.s, "source": self.source, "origin": self.origin}

    def line(self) -> str:
        """One line for people: '1 ms (device: ...)'."""
        return f"{self.s * 1e3:g} ms ({self.origin}: {self.source})"


NONE = DeviceDelay()


def checked(s, what: str = "device delay") -> float:
    """``s`` as a float in [0, MAX_DELAY_S] s, or one UserError naming ``what``."""
    ok = is_number(s)
    if not ok or not 0.0 <= s <= MAX_DELAY_S:
        raise UserError(f"{what} must be a number of seconds in [0, {MAX_DELAY_S:g}], got {s!r}")
    return float(s)


def given(s: float, source: str = "given") -> DeviceDelay:
    return DeviceDelay(checked(s), source, "given")


def resolve(rig=None, description=None, explicit: float | None = None) -> DeviceDelay:
    """The run's device delay (module doc for the order). ``rig``: a ``labbench.rig.Rig``;
    ``description``: the device's ``DeviceDescription``; ``explicit``: a given value [s]."""
    if explicit is not None:
        return given(explicit)
    if rig is not None and rig.measured_td_s is not None:
        origin = f" ({rig.measured_td_from})" if rig.measured_td_from else ""
        return DeviceDelay(float(rig.measured_td_s), f"{rig.source}: [rig] measured_td_s{origin}", "rig")
    declared = getattr(description, "device_delay_s", 0.0) or 0.0
    if declared > 0:
        why = getattr(description, "device_delay_why", "") or "declared by the device"
        return DeviceDelay(float(declared), f"{description.kind}: {why}", "device")
    return NONE


def from_dict(d) -> DeviceDelay | None:
    """A recorded ``device_delay`` dict back (None when it is not one: hostile content is
    not trusted)."""
    if not isinstance(d, dict):
        return None
    s = d.get("s")
    try:
        s = checked(s)
    except UserError:
        return None
    origin = d.get("origin") if d.get("origin") in ORIGINS else "given"
    source = d.get("source") if isinstance(d.get("source"), str) else "recorded"
    return DeviceDelay(s, source, origin)


def from_start(start: dict) -> DeviceDelay:
    """The device delay a session's start record says its run used (older sessions: the
    pre-check's ``measured_td``); NONE when it says none."""
    if not isinstance(start, dict):
        return NONE
    got = from_dict(start.get("device_delay"))
    if got is not None:
        return got
    pre = start.get("precheck")
    old = pre.get("measured_td") if isinstance(pre, dict) else None
    if isinstance(old, dict) and old.get("td_s"):
        got = from_dict({"s": old.get("td_s"), "source": old.get("source"), "origin": "rig"})
        if got is not None:
            return got
    return NONE


def from_meta(meta: dict) -> float:
    """The device delay [s] of analysis metadata (``device_delay_s``; the older
    ``td_measured``); 0 when absent. A bad value is one UserError."""
    for key in (META_KEY, _OLD_META_KEY):
        if isinstance(meta, dict) and meta.get(key) is not None:
            try:
                v = float(meta[key])
            except (TypeError, ValueError):
                raise UserError(f"metadata {key}={meta[key]!r} is not a number") from None
            return checked(v, f"metadata {key}")
    return 0.0
