"""Simulated rig: a mass-damper handle behind the ``labbench.device.Device`` interface.

Timing is that of the exact sampled-data model (``labbench.model.linear``, docs/conventions.md): ``read()``
number k returns x[k], the position at the start of step k; the force given to
``command()`` after it is held over step k; the next ``read()`` advances the
plant by exactly one T (``labbench.model.linear.zoh_matrices``) and returns x[k+1].
With no friction, noise, quantisation or extra delay a run through
``labbench.loop.chain`` therefore equals the sampled model to rounding.

Options (rig table ``[sim]``, overridden by keyword options of ``open_sim``):
``m`` [kg], ``b`` [N s/m], ``coulomb_n`` [N] Coulomb friction (stick/slip solved
inside the step, ``labbench.sim_backend.friction``), ``quantize`` (report positions in
encoder counts of ``rig.metres_per_count``), ``force_noise_n`` [N] std of white
noise added to the applied force, ``extra_delay_samples`` whole samples of
actuator latency and ``extra_delay_fraction`` in [0, 1) more (each step then
holds the previous command for that fraction of T first: the latency model of
``labbench.model.linear``; with friction each of the two stretches is solved exactly),
``cogging_n`` [N] and ``cogging_period_m`` [m] a motor's detent force
``cogging_n sin(2 pi x / cogging_period_m)`` against the handle (substeps,
``labbench.sim_backend.friction.Cogging``), ``x0_m`` / ``v0_m_s`` initial state.

``paced`` (all simulated backends: sim, sim-canopen, sim-serial, avr-sim; ``paced_by_rig``):
run at the sample time of the wall clock, under the rig's ``[realtime]`` settings, as the
rig's hardware would, instead of lock-step. Default false: a lock-step run's record is the
same on any machine and under any load (the peers share this machine's CPU with the
loop, and a paced run of them faults on a loaded machine as hardware would not); a
paced run is for what timing shows. ``--realtime`` (CLI) or ``realtime=True`` (a
factory's argument) asks for it too, and an explicit ``realtime`` wins over the rig.

Truth that may differ from the rig file (so commissioning can be tested against a rig
file that is wrong in a known way; ``true_geometry``): ``sign`` (1 or -1: the way the
encoder really counts, relative to a positive force; default the rig's belief
``[rig] position_sign``), ``counts_per_rev`` and ``lever_arm_m`` (the real ones;
default the rig's). The command is a force at the handle as the rig believes it:
the joint gets ``force * rig.lever_arm_m`` and the handle feels that over the true
lever arm; the reported position is the true encoder count times the rig's
``position_per_count``. Behind a protocol peer (``as_plant=True``: the simulated
drive and board) the plant is the bare mass-damper in true handle units and the peer
applies the geometry.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from labbench.device import (ESTOP_STATE, DeviceDescription, DeviceFault, DeviceStatus,
                             Sample)
from labbench import scales
from labbench.errors import UserError, nearest_hint
from labbench.loop.realtime import sleep_until
from labbench.model.ve import DEFAULT_PLANT, Plant
from labbench.sim_backend.friction import Cogging, cogged_step, held_step, reversing_step
from labbench.model.linear import latency_inputs, zoh_matrices

_NOISE_STREAM = 0x4E01  # key of the force-noise stream (labbench.protocols draw from the seed alone)

# name -> (default, check, what the check demands)
_OPTIONS = {
    "m": (DEFAULT_PLANT.m, lambda v: _num(v) and v > 0, "a positive number [kg]"),
    "b": (DEFAULT_PLANT.b, lambda v: _num(v) and v >= 0, "a number >= 0 [N s/m]"),
    "coulomb_n": (0.0, lambda v: _num(v) and v >= 0, "a number >= 0 [N]"),
    "quantize": (False, lambda v: isinstance(v, bool), "true or false"),
    "force_noise_n": (0.0, lambda v: _num(v) and v >= 0, "a number >= 0 [N]"),
    "extra_delay_samples": (0, lambda v: isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 1000,
                            "a whole number of samples in 0..1000"),
    "extra_delay_fraction": (0.0, lambda v: _num(v) and 0 <= v < 1, "a number in [0, 1) [samples]"),
    "cogging_n": (0.0, lambda v: _num(v) and 0 <= v <= 1e3, "a number in [0, 1000] [N]"),
    "cogging_period_m": (None, lambda v: _num(v) and 1e-6 <= v <= 10, "a number in [1e-6, 10] [m]"),
    "x0_m": (0.0, lambda v: _num(v), "a number [m]"),
    "sign": (None, lambda v: isinstance(v, int) and not isinstance(v, bool) and v in (1, -1),
             "1 or -1"),
    "counts_per_rev": (None, None, "labbench.scales"),  # the truth: as a rig's, physical
    "lever_arm_m": (None, None, "labbench.scales"),
    "v0_m_s": (0.0, lambda v: _num(v), "a number [m/s]"),
    "paced": (False, lambda v: isinstance(v, bool), "true or false"),
}
_NOISE_BLOCK = 4096
ESTOP_LATCHED = 1  # bit of a sample's flags: the emergency stop is latched, force is off


def _num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def sim_options(rig, **options) -> dict:
    """Validated simulator settings: defaults < ``rig.section("sim")`` < ``options``."""
    settings = {name: spec[0] for name, spec in _OPTIONS.items()}
    for origin, table in ((f"{rig.source}: [sim]", rig.section("sim")), ("sim option", options)):
        for name, value in table.items():
            if name not in _OPTIONS:
                raise UserError(f"{origin} {name}: unknown ({nearest_hint(name, _OPTIONS)})")
            check = _OPTIONS[name][1]
            if check is None:
                value = scales.SCALES[("sim", name)].check(value, f"{origin} {name}")
            elif not check(value):
                raise UserError(f"{origin} {name} must be {_OPTIONS[name][2]}, got {value!r}")
            settings[name] = value
    for name in ("m", "b", "coulomb_n", "force_noise_n", "x0_m", "v0_m_s", "extra_delay_fraction",
                 "cogging_n"):
        settings[name] = float(settings[name])
    if settings["cogging_n"] and settings["cogging_period_m"] is None:
        raise UserError("sim cogging_n needs cogging_period_m (the detents' spacing at the handle) [m]")
    Plant(settings["m"], settings["b"])  # within the physical range (1e308 overflows the plant)
    return settings


@dataclass(frozen=True)
class Geometry:
    """The rig's true calibration: encoder direction, handle metres per count, lever arm."""

    sign: int
    metres_per_count: float
    lever_arm_m: float

    def force_gain(self, rig) -> float:
        """True handle force per newton the rig believes it commands (1.0 when true)."""
        return rig.lever_arm_m / self.lever_arm_m

    def position_gain(self, rig, believed_sign: int) -> float:
        """Reported metres per true metre for a driver that multiplies counts by
        ``believed_sign * rig.metres_per_count`` (1.0 when the rig file is true)."""
        return believed_sign * self.sign * rig.metres_per_count / self.metres_per_count


def true_geometry(rig, settings: dict, believed_sign: int | None = None) -> Geometry:
    """The truth of ``settings`` (``sim_options``) where the rig file may be wrong;
    ``believed_sign``: the sign the device's driver gives counts (default the rig's
    ``position_sign``), which is the encoder's true sign unless ``sign`` says otherwise."""
    believed = rig.position_sign if believed_sign is None else believed_sign
    sign = believed if settings.get("sign") is None else settings["sign"]
    lever = rig.lever_arm_m if settings.get("lever_arm_m") is None else float(settings["lever_arm_m"])
    counts = rig.counts_per_rev if settings.get("counts_per_rev") is None else float(settings["counts_per_rev"])
    return Geometry(sign, 2 * math.pi * lever / counts, lever)


def paced_by_rig(rig, realtime: bool | None) -> bool:
    """Whether a simulated backend runs paced: ``realtime`` when given, else the rig's
    ``[sim] paced`` (module doc)."""
    return bool(realtime) if realtime is not None else bool(rig.section("sim").get("paced"))


def open_sim(rig, realtime: bool | None = None, seed: int | None = None,
             **options) -> SimDevice:
    """Open the simulated device for ``rig`` (registered as "sim" in ``labbench.devices``);
    ``realtime`` None: the rig's ``[sim] paced``."""
    return SimDevice(rig, realtime=paced_by_rig(rig, realtime), seed=seed, **options)


class SimDevice:
    """Simulated 1-DOF handle; see the module docstring for timing and options.

    ``read_raw(timeout)`` is the allocation-free form of ``read``: it returns the
    tuple ``(seq, t_s, position_m, flags)``; ``labbench.loop.chain.run_loop`` uses it
    when a device offers it. ``emergency_stop()`` may be called from any thread:
    the force applied from the step under way on is zero, and stays zero.
    """

    def __init__(self, rig, realtime: bool = False, seed: int | None = None,
                 as_plant: bool = False, **options):
        self.options = sim_options(rig, **options)
        self.rig, self.realtime, self.seed = rig, bool(realtime), seed
        o = self.options
        self.T = T = rig.sample_time_s
        Ad, Bd = zoh_matrices(o["m"], o["b"], T)
        self._coef = (*Ad.ravel().tolist(), *Bd.tolist())  # a11, a12, a21, a22, b1, b2
        # the geometry (module doc); a peer applies it itself
        self.geometry = geo = true_geometry(rig, o)
        self._force_gain = 1.0 if as_plant else geo.force_gain(rig)
        self._x_gain = 1.0 if as_plant else geo.position_gain(rig, rig.position_sign)
        self._q = geo.metres_per_count if o["quantize"] else 0.0  # a true count
        self._fc = o["coulomb_n"]
        self._noise_std = o["force_noise_n"]
        # A stream of its own: a run passes one seed to the device and to the protocol, and
        # force noise equal to (a multiple of) the excitation would bias Z at coherence 1.
        self._rng = np.random.default_rng(None if seed is None else [int(seed), _NOISE_STREAM])
        self._noise: list[float] = []
        self._noise_i = 0
        self._delay = [0.0] * o["extra_delay_samples"]
        # input vector of the previous command, held for the first extra_delay_fraction of a step
        self._early = (latency_inputs(Plant(o["m"], o["b"]), T, o["extra_delay_fraction"])[1].tolist()
                       if o["extra_delay_fraction"] else None)
        self._delay_i = 0
        # Friction with a fractional delay, or cogging: each step is held stretches (the
        # previous command over the first fraction of T, then this one) solved one by one
        alpha = o["extra_delay_fraction"]
        self._cogging = (Cogging(o["cogging_n"], float(o["cogging_period_m"]), o["m"])
                         if o["cogging_n"] else None)
        self._stretches = ((alpha * T, True), ((1.0 - alpha) * T, False)) if alpha else ((T, False),)
        self._stretched = bool(self._cogging or (alpha and self._fc))
        self.x, self.v = o["x0_m"], o["v0_m_s"]  # true state at the start of the current step
        self.applied_n = 0.0  # force applied over the last completed step (after noise/gating)
        self._u = 0.0
        self._k = -1  # index of the last sample returned
        self._t0 = None
        self.enabled = False
        self.estopped = False
        self._active = False  # enabled and not emergency-stopped: read at apply time
        self.closed = False
        self.health = 0  # sample flags: ESTOP_LATCHED once emergency-stopped

    # -- Device protocol -------------------------------------------------------------
    def describe(self) -> DeviceDescription:
        return DeviceDescription(
            kind="sim", name=self.rig.name, sample_time_s=self.T,
            force_limit_n=self.rig.force_limit_n,
            position_limits_m=tuple(self.rig.position_limits_m),
            details={**self.options, "metres_per_count": self.rig.metres_per_count,
                     "paced": self.realtime, "seed": self.seed},
            simulated="simulated mass-damper handle (the exact sampled model)",
        )

    def enable(self, timeout: float = 1.0) -> None:
        self._check_open()
        if self.estopped:
            raise DeviceFault("emergency stop latched: close and reopen the device")
        self.enabled = self._active = True

    def disable(self, timeout: float = 1.0) -> None:
        self.enabled = self._active = False
        self._u = 0.0

    def emergency_stop(self) -> None:
        self._active = False
        self.estopped = True
        self._u = 0.0
        self.health = ESTOP_LATCHED

    def command(self, force_n: float) -> None:
        self._u = force_n * self._force_gain

    def status(self) -> DeviceStatus:
        state = ("closed" if self.closed else ESTOP_STATE if self.estopped
                 else "enabled" if self.enabled else "disabled")
        return DeviceStatus(state)

    def read(self, timeout: float) -> Sample:
        return Sample(*self.read_raw(timeout))

    def read_raw(self, timeout: float) -> tuple:
        """Next sample as ``(seq, t_s, position_m, flags)``; advances the plant one T.

        The step holds the applied force: exact ZOH for the linear part, Coulomb
        friction solved inside the step. Written out in one method (a helper is
        called only in a step where the velocity reaches zero, or one made of held
        stretches: friction with a fractional delay, cogging): it runs once per
        simulated sample.
        """
        if self.closed:
            raise DeviceFault("simulated device is closed")
        k = self._k + 1
        if self.realtime:
            self._pace(k, timeout)
        self._k = k
        if k:
            u = self._u
            if self._delay:
                d, i = self._delay, self._delay_i
                d[i], u = u, d[i]
                self._delay_i = i + 1 if i + 1 < len(d) else 0
            if not self._active:
                u = 0.0
            elif self._noise_std:
                if self._noise_i == len(self._noise):
                    self._noise = self._rng.normal(0.0, self._noise_std, _NOISE_BLOCK).tolist()
                    self._noise_i = 0
                u += self._noise[self._noise_i]
                self._noise_i += 1
            u_early, self.applied_n = self.applied_n, u
            x, v = self.x, self.v
            a11, a12, a21, a22, b1, b2 = self._coef
            fc = self._fc
            if self._stretched:
                self.x, self.v = x, _ = self._held_stretches(x, v, u_early, u)
            elif not fc:
                self.v = a21 * x + a22 * v + b2 * u
                self.x = x = a11 * x + a12 * v + b1 * u
                if self._early:  # x+ = Ad x + G_late u + G_early u_early, G_late = Bd - G_early
                    self.v += self._early[1] * (u_early - u)
                    self.x = x = x + self._early[0] * (u_early - u)
            elif v == 0.0 and -fc <= u <= fc:
                pass  # at rest and the force cannot break it loose
            else:
                ue = u - fc if v > 0.0 or (v == 0.0 and u > 0.0) else u + fc
                vn = a21 * x + a22 * v + b2 * ue
                if (v > 0.0 and vn <= 0.0) or (v < 0.0 and vn >= 0.0):
                    o = self.options
                    self.x, self.v = x, _ = reversing_step(x, v, u, fc, self.T, o["m"], o["b"])
                else:
                    self.x = x = a11 * x + a12 * v + b1 * ue
                    self.v = vn
        else:
            x = self.x
        q = self._q
        if q:  # whole true counts (then read as the rig believes counts: _x_gain)
            x = math.floor(x / q + 0.5) * q
        return k, k * self.T, x * self._x_gain, self.health

    def close(self) -> None:
        self.emergency_stop()
        self.closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- internals -------------------------------------------------------------------
    def _held_stretches(self, x: float, v: float, u_early: float, u: float) -> tuple[float, float]:
        """State after one step made of held stretches (``__init__``), each solved with
        friction (and cogging) by ``labbench.sim_backend.friction``."""
        o, fc, cog = self.options, self._fc, self._cogging
        for h, early in self._stretches:
            f = u_early if early else u
            if cog is None:
                x, v = held_step(x, v, f, fc, h, o["m"], o["b"])
            else:
                x, v = cogged_step(x, v, f, fc, h, o["m"], o["b"], cog)
        return x, v

    def _pace(self, k: int, timeout: float) -> None:
        """Wait until sample k is due at ``t0 + k T`` (``labbench.loop.realtime.sleep_until``:
        sleep, then spin the last 150 us, so the sample is on time to a few us).

        The schedule starts at the first read, and starts again at any read more than
        one period past its due time: time nobody was reading (idle after open or
        between runs) is not a backlog to deliver unpaced. Lateness under one period
        (sleep overshoot, jitter) is made up. The same rule as the paced CANopen
        driver's SYNC schedule (``labbench.drivers.canopen_drive``), which re-phases a late tick.
        """
        now = time.perf_counter()
        t0 = self._t0
        if t0 is None or now > t0 + (k + 1) * self.T:
            self._t0 = now - k * self.T  # sample k is due now
            return
        wait = t0 + k * self.T - now
        if wait > timeout:
            time.sleep(timeout)
            raise TimeoutError(f"no simulated sample within {timeout} s")
        if wait > 0:
            sleep_until(t0 + k * self.T)

    def _check_open(self) -> None:
        if self.closed:
            raise DeviceFault("simulated device is closed")
