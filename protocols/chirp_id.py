"""Chirp identification (paper sec. 4.1): VE off, a chirp force 0.1-25 Hz, fit f = m x'' + b x'.

The free mass-damper has an integrator, so a constant-amplitude force at
0.1 Hz would carry the handle far out of its window (|X/F| = 1/(w |b + j w m|)
is ~14 m/N there for the paper's Phantom). The force amplitude therefore
follows ``min(amplitude_n, x_max_m * w |b + j w m|)`` with the nominal plant
(``excitation.displacement_envelope``), and the plan is checked before enabling
by simulating the nominal plant exactly (ZOH) against the rig's position and
velocity limits.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter, ss2tf

from labbench.errors import UserError
from labbench.ve import Plant, VirtualEnvironment
from labbench.protocols import excitation
from labbench.protocol import (
    MAX_DURATION_S,
    MAX_FORCE_N,
    Config,
    ProtocolBase,
    Segment,
    check_plant_fields,
    choice,
    number,
)
from labbench.theory import zoh_matrices

METHODS = ("l2", "l1")


@dataclass(frozen=True)
class ChirpIdConfig(Config):
    """Chirp identification: VE off, chirp force f0-f1 Hz, l2/l1 fit of m, b (sec. 4.1)."""

    f0_hz: float = 0.1
    f1_hz: float = 25.0
    sweep: str = "log"
    amplitude_n: float = 1.0  # peak force cap
    x_max_m: float = 0.02  # steady-state displacement cap of the envelope
    duration_s: float = 60.0
    fade_s: float = 1.0  # raised-cosine fade in and out
    model: str = "auto"  # passed to labbench.analysis.identify
    methods: tuple = METHODS  # fits to run: "l2" (least squares), "l1" (least absolute)
    sample_time_s: float = 0.001
    plant_m_kg: float | None = None  # nominal plant for the envelope (None: the rig's)
    plant_b: float | None = None

    def check(self):
        self._set("f0_hz", number("f0_hz", self.f0_hz, "Hz", lo=0, lo_open=True))
        self._set("f1_hz", number("f1_hz", self.f1_hz, "Hz", lo=0, lo_open=True))
        self._set("sample_time_s", number("sample_time_s", self.sample_time_s, "s", lo=0, lo_open=True))
        nyquist = 0.5 / self.sample_time_s
        if not self.f0_hz < self.f1_hz:
            raise UserError(f"f0_hz ({self.f0_hz:g} Hz) must be below f1_hz ({self.f1_hz:g} Hz)")
        if self.f1_hz >= nyquist:
            raise UserError(f"f1_hz must be below the Nyquist frequency {nyquist:g} Hz, got {self.f1_hz:g}")
        choice("sweep", self.sweep, excitation.SWEEPS)
        self._set("amplitude_n", number("amplitude_n", self.amplitude_n, "N", lo=0, lo_open=True,
                                        hi=MAX_FORCE_N))
        self._set("x_max_m", number("x_max_m", self.x_max_m, "m", lo=0, lo_open=True))
        self._set("duration_s", number("duration_s", self.duration_s, "s", lo=0, lo_open=True,
                                              hi=MAX_DURATION_S))
        self._set("fade_s", number("fade_s", self.fade_s, "s", lo=0, hi=self.duration_s / 2))
        from labbench.analysis.identify import MODEL_CHOICES  # checked now: not after the run

        choice("model", self.model, MODEL_CHOICES)
        if isinstance(self.methods, str):
            methods = (self.methods,)
        elif isinstance(self.methods, (list, tuple)):
            methods = tuple(self.methods)
        else:
            raise UserError(f"methods must be a list of l2, l1, got {self.methods!r}")
        if not methods:
            raise UserError("methods must name at least one of l2, l1")
        for m in methods:
            choice("methods", m, METHODS)
        self._set("methods", methods)
        check_plant_fields(self)
        if self.duration_s * self.f0_hz < 1:
            raise UserError(f"duration_s ({self.duration_s:g} s) must cover at least one period "
                            f"of f0_hz ({1 / self.f0_hz:g} s)")


class ChirpId(ProtocolBase):
    name = "chirp-id"

    Config = ChirpIdConfig
    config: ChirpIdConfig

    @property
    def ve(self) -> VirtualEnvironment:
        return VirtualEnvironment("none", T=self.config.sample_time_s)

    @property
    def n_samples(self) -> int:
        return round(self.config.duration_s / self.config.sample_time_s)

    def excitation(self, plant: Plant) -> np.ndarray:
        c = self.config

        def env(f_hz):
            return excitation.displacement_envelope(f_hz, plant.m, plant.b, c.x_max_m, c.amplitude_n)

        return excitation.chirp(self.n_samples, c.sample_time_s, c.f0_hz, c.f1_hz, env, c.sweep,
                                round(c.fade_s / c.sample_time_s))

    def check_plan(self, plant: Plant, rig=None) -> dict:
        """Simulate the nominal plant (exact ZOH) under the planned force; refuse a plan
        that leaves the rig's position window or exceeds its velocity/force limits."""
        f = self.excitation(plant)
        Ad, Bd = zoh_matrices(plant.m, plant.b, self.config.sample_time_s)
        # x[k+1] = Ad x[k] + Bd f[k], as two transfer functions run by lfilter (C speed).
        x, v = (_run_tf(ss2tf(Ad, Bd[:, None], C, [[0.0]]), f) for C in ([[1.0, 0.0]], [[0.0, 1.0]]))
        out = {"predicted_x_range_m": [float(x.min()), float(x.max())],
               "predicted_v_max_m_s": float(np.abs(v).max()),
               "force_peak_n": float(np.abs(f).max())}
        if rig is not None:
            lo, hi = rig.position_limits_m
            if x.min() < lo or x.max() > hi:
                raise UserError(
                    f"chirp would move the handle over [{x.min():.3g}, {x.max():.3g}] m, outside the "
                    f"rig's window [{lo:g}, {hi:g}] m (m = {plant.m:g} kg, b = {plant.b:g} N s/m): "
                    f"lower x_max_m ({self.config.x_max_m:g} m)")
            if np.abs(v).max() > rig.velocity_limit_m_s:
                raise UserError(
                    f"chirp would reach {np.abs(v).max():.3g} m/s, above the rig's velocity limit "
                    f"{rig.velocity_limit_m_s:g} m/s: lower amplitude_n or x_max_m")
            if np.abs(f).max() > rig.force_limit_n:
                raise UserError(f"amplitude_n {self.config.amplitude_n:g} N exceeds the rig's "
                                f"force limit {rig.force_limit_n:g} N")
        return {"plan": out}

    def segments(self, plant: Plant):
        yield Segment("chirp", self.ve, self.excitation(plant))

    def analyze(self, data: dict, meta: dict) -> dict:
        """l2 and l1 fits of f = m x'' + b x' (labbench.analysis.identify) on the force
        actually applied (the ``command`` channel: the VE is off, so it is the chirp
        after the safety envelope)."""
        from labbench.analysis.dataio import recording_from_arrays
        from labbench.analysis.identify import identify

        rec = recording_from_arrays(data["t"], data["command"], data["position"],
                                    {**meta, "protocol": self.name})
        fits = {method: identify(rec, model=self.config.model, method=method).as_dict()
                for method in self.config.methods}
        best = fits.get("l2") or fits[self.config.methods[0]]
        return {"identification": fits, "m": best["m"], "b": best["b"]}


def _run_tf(tf, u: np.ndarray) -> np.ndarray:
    num, den = tf
    return lfilter(num[0], den, u)
