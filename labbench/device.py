"""The one interface every rig offers: the simulator, the CANopen drive, the serial stream.

A device delivers timestamped, sequence-numbered position samples and takes a
force command. The haptic loop (``labbench.loop.chain``) is the only caller in a run.
All methods with a wait take a timeout. ``close()`` is safe to call twice.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

from labbench.errors import DeviceFault  # noqa: F401 - re-exported: drivers raise it from here


@dataclass(frozen=True)
class Sample:
    """One position sample at the handle.

    ``seq``: device sequence number (gaps = drops); ``t_s``: device time [s]
    (monotonic within a run); ``position_m``: SI position at the handle;
    ``flags``: device-specific health bits (0 = healthy).
    """

    seq: int
    t_s: float
    position_m: float
    flags: int = 0


# The one wording of a latched emergency stop, whatever the backend (``DeviceStatus.state``).
ESTOP_STATE = "E-STOP latched"


@dataclass(frozen=True)
class DeviceDescription:
    """What ``describe()`` returns: identity, units and limits at the handle.

    ``simulated``: what stands in for the hardware, e.g. "simulated CiA 402 drive in a
    thread of this process" ("" on hardware: every simulated backend says so here);
    ``details["paced"]``: whether samples come at the sample time of the wall clock
    (hardware, a paced simulator) or as fast as the host goes (lock-step).
    """

    kind: str  # "sim", "canopen", "serial", ...
    name: str
    sample_time_s: float
    force_limit_n: float
    position_limits_m: tuple[float, float]
    details: dict = field(default_factory=dict)
    # How the recorded force reached the plant (docs/analysis.md): "zoh", a commanded force
    # held over each sample interval; "sample", a force measured at the sample instants.
    force_hold: str = "zoh"
    # The device's own delay on the whole command [s] when the backend knows it (e.g. a
    # drive that applies a synchronous RPDO's torque at the next SYNC) and why:
    # labbench.model.device_delay (a rig file's measured value takes precedence).
    device_delay_s: float = 0.0
    device_delay_why: str = ""
    simulated: str = ""
    # Why the device applies no force at all ("" when it can), e.g. a position-only serial
    # board: every force protocol (commissioning included) is refused before it runs.
    cannot_act: str = ""

    @property
    def paced(self) -> bool:
        return bool(self.details.get("paced", True))

    def label(self) -> str:
        """One line for people: the name, what simulates it, and its pacing, e.g.
        "simulated CiA 402 drive, node 1: simulated drive in a thread, lock-step (as fast as
        the host goes)"."""
        pace = "paced at the sample time" if self.paced else "lock-step (as fast as the " \
                                                              "host goes)"
        return f"{self.name}: {self.simulated}, {pace}" if self.simulated else \
            f"{self.name} ({self.kind})"


@dataclass(frozen=True)
class DeviceStatus:
    """What a device tells about itself without bus traffic (``StatusReporting``)."""

    state: str  # "disabled" | "enabled" | ESTOP_STATE | "fault" | "closed"
    fault: str | None = None  # the latched fault, if any
    link: dict = field(default_factory=dict)  # link counters: CRC errors, lost frames, EMCY...


@runtime_checkable
class Device(Protocol):
    def describe(self) -> DeviceDescription: ...

    def enable(self, timeout: float = 1.0) -> None: ...

    def disable(self, timeout: float = 1.0) -> None: ...

    def emergency_stop(self) -> None:
        """Zero force at once and latch; never raises."""

    def read(self, timeout: float) -> Sample:
        """Block until the next sample (or raise TimeoutError / DeviceFault)."""

    def command(self, force_n: float) -> None:
        """Set the force applied from the next sample period on."""

    def close(self) -> None: ...

    def __enter__(self): ...

    def __exit__(self, *exc) -> None: ...


# Optional abilities: a backend offers them by having the method; callers test with
# isinstance (tests/test_device_conformance.py checks every registered backend).
@runtime_checkable
class RawReading(Protocol):
    def read_raw(self, timeout: float) -> tuple[int, float, float, int]:
        """``read()`` as a plain (seq, t_s, position_m, flags) tuple: no object per sample."""


@runtime_checkable
class Enabling(Protocol):
    def holding(self) -> bool:
        """True while the device holds its force at zero whatever it is commanded: after
        ``enable()`` until it confirms the power stage on (a CiA 402 drive stepping to
        OPERATION ENABLED over a few periods). The loop records those samples as gated, so
        the record never shows a force the device did not apply."""


@runtime_checkable
class StatusReporting(Protocol):
    def status(self) -> DeviceStatus:
        """State, latched fault and link counters, from memory (no bus traffic)."""


@runtime_checkable
class TimingProbe(Protocol):
    """What a sample's wait is made of, for the timing preflight (``labbench.loop.preflight``).

    ``timing_log``: None (off: nothing recorded, no cost), or a list that gets one
    ``(due_s, start_s, answer_s, wire_s)`` per sample: when it was due by the device's
    schedule, when the wait its stale limit measures began (a CANopen SYNC sent; a
    serial board's previous frame in), when the answer was in the host
    (``time.perf_counter`` seconds), and the round trip from the frames' own timestamps
    (NaN where unknown). ``stale_limit_s``: that limit (settable: the preflight relaxes
    it while it measures); ``stale_periods_max``: the most periods the rig may set."""

    timing_log: list | None
    stale_limit_s: float
    stale_periods_max: int
