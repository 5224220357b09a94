"""``labbench run commission``: is the rig file true? Direction, scale, delay, friction, K_max.

VE off, within the rig's force limit and position window: force doublets of both signs
(+A then -A for ``pulse_s`` each: the handle steps by about A pulse_s^2 / m and comes to
rest), then a short chirp-ID (the displacement envelope of ``protocols.chirp_id``). The
analysis is ``labbench.analysis.commission``; ``--write-rig`` is not part of this module.
About 22 s of rig time by default.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from labbench.errors import UserError
from labbench.protocol import (
    Config,
    ProtocolBase,
    Segment,
    check_plant_fields,
    integer,
    number,
    setting,
)
from labbench.protocols import excitation
from labbench.model.ve import Plant, VirtualEnvironment


# backends that drive the serial stream (labbench.drivers.serial_stream: [serial]
# command_units, "N" at the handle by default)
SERIAL_KINDS = ("serial", "sim-serial", "avr-sim")


@dataclass(frozen=True)
class CommissionConfig(Config):
    """Commissioning: doublets and a short chirp, VE off; checks the rig file (issue 20)."""

    pulse_n: float = setting(0.5, "force of each half of a doublet", "N")
    pulse_s: float = setting(0.02, "duration of each half of a doublet", "s")
    pulses: int = setting(4, "doublets, alternating in sign (2 to 100)")
    rest_s: float = setting(0.3, "rest after each doublet", "s")
    chirp_s: float = setting(20.0, "length of the chirp", "s")
    f0_hz: float = setting(0.2, "start frequency of the chirp", "Hz")
    f1_hz: float = setting(20.0, "end frequency of the chirp (below 0.45 / sample time)", "Hz")
    amplitude_n: float = setting(1.0, "peak force of the chirp", "N")
    x_max_m: float = setting(0.01, "largest steady displacement the chirp may cause", "m")
    sample_time_s: float = 0.001
    plant_m_kg: float | None = setting(None, "nominal device mass for the chirp's envelope; "
                                       "none: the rig's", "kg")
    plant_b: float | None = setting(None, "nominal device damping for the envelope; none: the "
                                    "rig's", "N s/m")

    def check(self):
        self._set("pulse_n", number("pulse_n", self.pulse_n, "N", lo=0, lo_open=True, hi=1000))
        self._set("pulse_s", number("pulse_s", self.pulse_s, "s", lo=self.sample_time_s, hi=1.0))
        self._set("pulses", integer("pulses", self.pulses, lo=2))
        if self.pulses > 100:
            raise UserError(f"pulses must be at most 100, got {self.pulses}")
        self._set("rest_s", number("rest_s", self.rest_s, "s", lo=0.05, hi=10.0))
        self._set("chirp_s", number("chirp_s", self.chirp_s, "s", lo=1.0, hi=100.0))
        self._set("f0_hz", number("f0_hz", self.f0_hz, "Hz", lo=0, lo_open=True))
        self._set("f1_hz", number("f1_hz", self.f1_hz, "Hz", lo=0, lo_open=True,
                                  hi=0.45 / self.sample_time_s))
        if not self.f0_hz < self.f1_hz:
            raise UserError(f"f0_hz ({self.f0_hz:g} Hz) must be below f1_hz ({self.f1_hz:g} Hz)")
        self._set("amplitude_n", number("amplitude_n", self.amplitude_n, "N", lo=0, lo_open=True, hi=1000))
        self._set("x_max_m", number("x_max_m", self.x_max_m, "m", lo=0, lo_open=True))
        check_plant_fields(self)


class Commission(ProtocolBase):
    name = "commission"
    Config = CommissionConfig
    config: CommissionConfig

    @property
    def ve(self) -> VirtualEnvironment:
        return VirtualEnvironment("none", T=self.config.sample_time_s)

    def _doublets(self):
        """(force, [(start, stop, first sign)]) of the pulse part."""
        c = self.config
        T = c.sample_time_s
        w, rest = round(c.pulse_s / T), round(c.rest_s / T)
        parts, marks, at = [], [], 0
        for i in range(c.pulses):
            s = 1.0 if i % 2 == 0 else -1.0
            parts.append(np.concatenate([np.full(w, s * c.pulse_n), np.full(w, -s * c.pulse_n),
                                         np.zeros(rest)]))
            marks.append((at, at + 2 * w + rest - 1, s))
            at += 2 * w + rest
        return np.concatenate(parts), marks

    def excitation(self, plant: Plant) -> np.ndarray:
        c = self.config
        T = c.sample_time_s

        def env(f_hz):
            return excitation.displacement_envelope(f_hz, plant.m, plant.b, c.x_max_m, c.amplitude_n)

        chirp = excitation.chirp(round(c.chirp_s / T), T, c.f0_hz, c.f1_hz, env, "log", round(1.0 / T))
        return np.concatenate([self._doublets()[0], chirp])

    @property
    def n_samples(self) -> int:
        c = self.config
        return len(self._doublets()[0]) + round(c.chirp_s / c.sample_time_s)

    def check_plan(self, plant: Plant, rig=None) -> dict:
        c = self.config
        if rig is not None and max(c.pulse_n, c.amplitude_n) > rig.force_limit_n:
            raise UserError(f"pulse_n {c.pulse_n:g} N / amplitude_n {c.amplitude_n:g} N exceed the "
                            f"rig's force limit {rig.force_limit_n:g} N")
        step = c.pulse_n * c.pulse_s**2 / plant.m  # each doublet's displacement, nominal plant
        return {"plan": {"doublet_step_m": step, "rig_time_s": self.n_samples * c.sample_time_s}}

    def segments(self, plant: Plant):
        yield Segment("commission", self.ve, self.excitation(plant))

    def analyze(self, data: dict, meta: dict) -> dict:
        from labbench.analysis import commission

        rig = meta.get("rig") or {}
        # a serial board may take the force at the handle ("N"): then the lever arm scales
        # the position only (labbench.analysis.commission module doc)
        serial = meta.get("device_kind") in SERIAL_KINDS
        units = ((rig.get("sections") or {}).get("serial") or {}).get("command_units", "N")
        via_lever = not serial or units == "N*m"
        return commission.analyze(
            data["t"], data["command"], data["position"], applied_doublets(self._doublets()[1], data),
            {"T": meta["T"], "nominal": meta["plant"], "device_delay_s": meta.get("device_delay_s"),
             "rig": rig, "force_via_lever": via_lever})

    def report_sections(self, session):
        """Page 1 is the readout's (each check's verdict with its numbers, the rig changes:
        ``labbench.readout.wording``); nothing more to add."""
        from labbench.report.blocks import ReportSections

        return ReportSections()


def applied_doublets(marks: list, data: dict) -> list:
    """The doublets the loop applied: the enable gate holds the force at zero until the
    excitation is near zero (``labbench.loop.chain``), so the first doublet, which starts at full
    force, never reaches the handle and says nothing of the direction (a true rig read
    "3 of 4 pulses moved with the force")."""
    from labbench.loop.safety import GATED

    flags = data.get("flags")
    if flags is None:
        return marks
    gated = (np.asarray(flags).astype(np.int64) & GATED) != 0
    return [m for m in marks if not gated[m[0]:m[1] + 1].any()]
