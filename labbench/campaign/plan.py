"""A campaign's plan: every point of a sweep spec as one run on one device, checked before
anything moves.

The spec is a sweep spec (``labbench.sweep.spec``: grid, cases, ranges, fixed values,
charts) of kind ``run``; its ``[sweep] device`` is the sweep's, a campaign runs on the
device it is given. A point's parameters go by name (``labbench.sweep.point.route``) to
the protocol's settings, to the rig (``sample_time_s``, ``force_limit_n``, ...: the
point's rig is the campaign's with those fields replaced) and, on a simulator only, to the
simulated device (``quantize``, ``coulomb_n``, ...). ``K_frac_k_max`` sets K as a fraction
of the exact sampled K_max of the point's VE on the campaign's plant with the rig's delay.

The plant every point is checked and predicted with is the campaign's (``Context``): the
one given, else the rig's last identified one, else its nominal one, so that every row's
prediction is made from one model. Before the first point the whole plan is checked:
every point's settings (one ``UserError`` for the first that cannot be made), the
commissioning gate (``labbench.commissioning.gate``, as ``labbench run`` applies it), and
the pre-check of each point (``labbench.protocol.precheck``); a point the pre-check calls
unstable is planned as *skipped* (its row says why) unless its protocol is the stability
probe, whose steps beyond the boundary are its purpose (its first step must be stable).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from labbench import commissioning, device_delay
from labbench.campaign.settings import CampaignSettings
from labbench.errors import UnstableVEError, UserError
from labbench.numfmt import fmt
from labbench.rig import Rig, rig_from_dict
from labbench.sweep.point import DEVICE_DELAY, K_FRACTION, route
from labbench.sweep.spec import Point, Spec, point_key
from labbench.ve import Plant

def is_simulator(device: str) -> bool:
    """A simulated backend (what a sweep accepts too): ``sim*`` or ``*-sim``."""
    return device.startswith("sim") or device.endswith("-sim")


@dataclass(frozen=True)
class Context:
    """What every point of a campaign shares: the device, the rig, the plant and what the
    rig's commissioning found."""

    device: str
    rig: Rig
    plant: Plant
    plant_from: str  # "given", "nominal", or the path of the chirp-ID session it was identified in
    simulated: bool
    settings: CampaignSettings
    commission: dict = field(default_factory=dict)  # {"session", "coulomb_n", ...} or {}
    skip_commissioning: bool = False
    identified_coulomb_n: float | None = None  # the plant's chirp-ID's Coulomb term, if any

    @property
    def coulomb_n(self) -> float | None:
        """The device's Coulomb friction (None: not known): the chirp-ID's that gave the plant,
        else the rig's last commissioning's estimate. The friction-aware stability boundary's
        (the stability probe's ``plant_coulomb_n``, unless the spec gives it)."""
        if self.identified_coulomb_n is not None:
            return self.identified_coulomb_n
        return self.commission.get("coulomb_n")

    @property
    def plant_label(self) -> str:
        """Where the plant came from, in words (the plan, the table's ``plant.from``)."""
        return self.plant_from if self.plant_from in ("given", "nominal") else \
            f"chirp-ID {self.plant_from}"

    def plant_record(self) -> dict | None:
        """The start record's ``plant_from`` of a point that runs this plant (None where the
        campaign's own settings gave it: their options say so)."""
        if self.plant_from == "given":
            return None
        where = {"nominal": True} if self.plant_from == "nominal" else {"session": self.plant_from}
        return {"m": self.plant.m, "b": self.plant.b, **where}

    def as_dict(self) -> dict:
        delay = device_delay.resolve(self.rig)
        return {"device": self.device, "rig": self.rig.name, "rig_source": self.rig.source,
                "plant": {"m": self.plant.m, "b": self.plant.b, "from": self.plant_label},
                "device_delay": delay.as_dict(), "simulated": self.simulated,
                "pause_s": self.settings.pause_s, "commission": self.commission}


@dataclass
class PlannedPoint:
    """One point as it will run: its key (``labbench.sweep.spec.point_key``), the protocol
    made from its settings, its rig, the simulator's options, and what the plan found."""

    point: Point
    key: str
    protocol_name: str
    options: dict
    rig: Rig
    device_options: dict
    protocol: object
    plant_from: dict | None = None  # where the plant in ``options`` came from (its start record's)
    skipped: str | None = None  # the pre-check's refusal: the point is not run
    est_s: float = 0.0  # device time [s] (an upper bound for an adaptive protocol)
    peak_force_n: float = 0.0  # largest exogenous force planned [N]
    max_k: float = 0.0  # stiffest VE it renders [N/m]

    @property
    def label(self) -> str:
        p = self.point
        parts = [f"{k}={v}" for k, v in p.tags.items()] + [
            f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}"
            for k, v in p.params.items() if k in self.varying]
        return ", ".join(parts) or f"point {p.index}"

    varying: tuple = ()  # the parameters that differ between points (for labels)


@dataclass
class Plan:
    spec: Spec
    context: Context
    points: list[PlannedPoint]

    @property
    def target(self) -> dict:
        return target(self.spec, self.context)

    def summary(self, keys_done: set | None = None) -> dict:
        """Points, device time, the largest force and stiffness commanded, of the points
        still to run (all when ``keys_done`` is None)."""
        todo = [p for p in self.points if not keys_done or p.key not in keys_done]
        run = [p for p in todo if p.skipped is None]
        pause = self.context.settings.pause_s
        return {"points": len(self.points), "to_run": len(run),
                "skipped": len(todo) - len(run), "done": len(self.points) - len(todo),
                "device_s": sum(p.est_s for p in run),
                "est_s": sum(p.est_s for p in run) + pause * max(len(run) - 1, 0),
                "peak_force_n": max((p.peak_force_n for p in run), default=0.0),
                "force_limit_n": max((p.rig.force_limit_n for p in run), default=0.0),
                "max_k": max((p.max_k for p in run), default=0.0)}


def describe(plan: Plan, done: set, where) -> list[str]:
    """What a person sees before a campaign starts (the CLI prints it, the window shows it):
    the points, those already in the table ``where``, the time, the largest force and
    stiffness it will command, the plant."""
    s = plan.summary(done)
    c = plan.context
    kind = "simulator" if c.simulated else "real hardware"
    return [f"campaign {plan.spec.name} on {c.device} ({kind}), rig {c.rig.name!r}: "
            f"{s['points']} points, {s['done']} already in {where}, {s['to_run']} to run, "
            f"{s['skipped']} skipped by the pre-check",
            f"  estimated {fmt(s['est_s'] / 60, 3)} min ({fmt(s['device_s'] / 60, 3)} min "
            f"device time, pause {fmt(c.settings.pause_s)} s between points)",
            f"  largest force planned {fmt(s['peak_force_n'])} N (every command clamped at "
            f"{fmt(s['force_limit_n'])} N), stiffest VE {fmt(s['max_k'])} N/m",
            f"  plant m = {fmt(c.plant.m)} kg, b = {fmt(c.plant.b)} N s/m ({c.plant_label})"]


def commission_facts(directory, rig_name: str, on_skip=None) -> dict:
    """What the rig's newest successful commissioning in ``directory`` found (``{}``: none):
    its session, Coulomb estimate, counts/rev (if the encoder is wrong) and delay."""
    from labbench.session_catalogue import last_results

    got = last_results(directory, rig_name, "commission", on_skip=on_skip)
    if got is None:
        return {}
    res, path = got
    return {"session": path, "coulomb_n": (res.get("friction") or {}).get("coulomb_n"),
            "counts_per_rev": (res.get("scale") or {}).get("counts_per_rev_if_encoder"),
            "delay_samples": (res.get("delay") or {}).get("delay_samples")}


def target(spec: Spec, context: Context) -> dict:
    """What a campaign point's key depends on besides its parameters: the protocol, the
    device and the rig (the same point on another rig is another measurement)."""
    return {"kind": "campaign", "protocol": spec.protocol, "device": context.device,
            "rig": context.rig.name}


def make_plan(spec: Spec, context: Context) -> Plan:
    """Every point of ``spec`` on ``context``'s device, checked (module doc)."""
    if spec.kind != "run":
        raise UserError(f"{spec.source}: a campaign runs a protocol: [sweep] kind must be run")
    points = spec.points()
    varying = tuple(k for k in dict.fromkeys(k for p in points for k in p.params)
                    if len({repr(p.params.get(k)) for p in points}) > 1)
    tgt = target(spec, context)
    planned = []
    for p in points:
        pp = _plan_point(spec, context, p, tgt)
        pp.varying = varying
        planned.append(pp)
    return Plan(spec, context, planned)


def _plan_point(spec: Spec, context: Context, point: Point, tgt: dict) -> PlannedPoint:
    from labbench.protocol import precheck
    from labbench.registry import make_protocol, protocol_class

    where = f"{spec.source}: point {point.index}"
    r = route(spec.protocol, point.params)
    if DEVICE_DELAY in r["sweep"]:
        raise UserError(f"{where}: {DEVICE_DELAY} sets a sweep simulator's delay; a campaign "
                        "measures the device it runs on (the rig's measured_td_s is its delay)")
    dev = {k: v for k, v in r["device"].items() if k != "seed"}
    if dev and not context.simulated:
        raise UserError(f"{where}: {', '.join(sorted(dev))}: not a setting of protocol "
                        f"{spec.protocol} or of the rig (a simulator's options are for simulators)")
    seed = r["device"].get("seed")
    rig = point_rig(context.rig, r["rig"], where)
    fields = set(protocol_class(spec.protocol).Config.__dataclass_fields__)
    opts = {k: v for k, v in r["protocol"].items() if k != "sample_time_s"}  # the rig's
    plant_from = None  # the start record's: a plant the point's own settings give says so itself
    if "plant_m_kg" in fields and "plant_m_kg" not in opts and "plant_b" not in opts:
        opts.update(plant_m_kg=context.plant.m, plant_b=context.plant.b)
        plant_from = context.plant_record()
    if "plant_coulomb_n" in fields and "plant_coulomb_n" not in opts and context.coulomb_n:
        opts["plant_coulomb_n"] = context.coulomb_n
    plant = Plant(opts.get("plant_m_kg", context.plant.m), opts.get("plant_b", context.plant.b))
    delay = device_delay.resolve(rig)
    try:
        if K_FRACTION in r["sweep"]:
            opts["K"] = _k_from_fraction(spec.protocol, opts, rig, plant, delay.s,
                                         r["sweep"][K_FRACTION])
        protocol = make_protocol(spec.protocol, sample_time_s=rig.sample_time_s, **opts)
    except UserError as exc:
        raise UserError(f"{where}: {exc}") from None
    commissioning.gate(protocol.vetted_ves(plant), rig, context.simulated,
                       context.skip_commissioning)
    pp = PlannedPoint(point, point_key(tgt, point.params, point.tags), spec.protocol, opts, rig,
                      {**dev, **({"seed": seed} if seed is not None else {})}, protocol,
                      plant_from=plant_from)
    try:
        report = precheck(protocol, plant, rig, delay)
    except UnstableVEError as exc:  # the probe's first step is vetted, its later ones its point
        pp.skipped = f"pre-check: {exc}"
        return pp
    pp.est_s = float(protocol.n_samples) * rig.sample_time_s
    pp.peak_force_n, pp.max_k = _extent(protocol, plant, report)
    return pp


def point_rig(base: Rig, fields: dict, where: str = "point") -> Rig:
    """``base`` with the ``[rig]`` fields of a point replaced, validated as a rig file is."""
    if not fields:
        return base
    common = {k: v for k, v in base.as_dict().items() if k not in ("sections", "source")}
    common = {k: list(v) if isinstance(v, tuple) else v for k, v in common.items()
              if v is not None}
    common.update(fields)
    return rig_from_dict({"rig": common, **base.sections}, source=f"{base.source} ({where})")


def _k_from_fraction(name: str, opts: dict, rig: Rig, plant: Plant, latency: float, frac) -> float:
    from labbench.model import linear
    from labbench.registry import make_protocol

    if "K" in opts:
        raise UserError(f"give K or {K_FRACTION}, not both")
    if isinstance(frac, bool) or not isinstance(frac, (int, float)) or not frac > 0:
        raise UserError(f"{K_FRACTION} must be a number > 0, got {frac!r}")
    probe = make_protocol(name, sample_time_s=rig.sample_time_s, **{**opts, "K": 1.0})
    k = linear.k_max(plant, probe.ve, latency=latency)
    if k is None or not math.isfinite(k) or k <= 0:
        raise UserError(f"{K_FRACTION}: the VE has no finite stable K on this plant")
    return float(frac) * k


def _extent(protocol, plant: Plant, report: dict) -> tuple[float, float]:
    """(largest exogenous force, stiffest K) the point will command: the pre-check's plan
    where it has one (the probe's pulses and last step), else the first segment's
    excitation and the VEs it vets."""
    plan = report.get("plan") or {}
    peak = max(plan.get("pulse_n") or [0.0])
    k = max([ve.K for ve in protocol.vetted_ves(plant)] + [(plan.get("last") or {}).get("K", 0.0)])
    if "pulse_n" not in plan:
        gen = protocol.segments(plant)
        try:
            first = next(gen)
            peak = max(peak, float(np.max(np.abs(first.excitation), initial=0.0)))
        except StopIteration:
            pass
        finally:
            gen.close()
    return peak, float(k)
