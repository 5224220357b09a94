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
prediction is made from one model. Points are planned as they are asked for, as a sweep's
(a 10^6-point spec starts at once in little memory; the list took 19.5 s and 719 MB before
its first point could be refused): ``make_plan`` checks every distinct set of parameter
names first (``check_names``: a name nothing knows stops the campaign before any point);
``Plan.plan_point`` makes one point's settings (those that cannot be made are its
``refused`` reason: its row says why, as a sweep's), applies the commissioning gate
(``labbench.commissioning.gate``, as ``labbench run`` does) and the pre-check
(``labbench.protocol.precheck``); a point the pre-check calls unstable is planned as
*skipped* (its row says why) unless its protocol is the stability probe, whose steps beyond
the boundary are its purpose (its first step must be stable). On real hardware every point
is planned before anything moves (``describe``: the operator sees the whole plan).
"""
from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from labbench import commissioning
from labbench.model import device_delay
from labbench.rig import CampaignSettings
from labbench.errors import UnstableVEError, UserError
from labbench.readout.escape import one_line
from labbench.readout.numfmt import fmt
from labbench.rig import Rig, rig_from_dict
from labbench.sweep.point import DEVICE_DELAY, K_FRACTION, route
from labbench.sweep.spec import Point, Spec, point_key
from labbench.model.ve import Plant

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
    refused: str | None = None  # why its settings cannot be made (``protocol`` is None then)
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
    """A spec's points on a context's device, planned as they are asked for (``plan_point``):
    a 10^6-point spec holds no list (``points`` makes one, for a small spec shown whole)."""

    spec: Spec
    context: Context

    @property
    def target(self) -> dict:
        return target(self.spec, self.context)

    def key(self, point: Point) -> str:
        return point_key(self.target, point.params, point.tags)

    @functools.cached_property
    def varying(self) -> tuple:
        """The parameters that differ between points (for labels), from the spec's axes."""
        s = self.spec
        names = [k for k, v in s.grid.items() if len(v) > 1] + list(s.ranges)
        for cases in s.cases.values():
            for k in dict.fromkeys(k for _, p in cases for k in p):
                if len({repr(p.get(k)) for _, p in cases}) > 1:
                    names.append(k)
        return tuple(dict.fromkeys(names))

    def plan_point(self, point: Point) -> PlannedPoint:
        """``point`` as it will run; settings that cannot be made are its ``refused`` reason
        (its row says so: the campaign goes on), the commissioning gate and a simulator's
        option on real hardware one UserError (``check_names`` finds them first)."""
        pp = _plan_point(self.spec, self.context, point, self.target)
        pp.varying = self.varying
        return pp

    def iter_points(self) -> Iterator[PlannedPoint]:
        for point in self.spec.iter_points():
            yield self.plan_point(point)

    @functools.cached_property
    def points(self) -> list[PlannedPoint]:
        """Every point planned, as a list (a window showing a small spec whole)."""
        return list(self.iter_points())

    def summary(self, keys_done=None, progress: Callable[[int, int], None] | None = None) -> dict:
        """Points, device time, the largest force and stiffness commanded, of the points
        still to run (all when ``keys_done`` is None; anything with ``in``), every point
        planned once and let go (``progress(n, total)`` hears how far)."""
        total, pause = self.spec.count(), self.context.settings.pause_s
        s = {"points": 0, "to_run": 0, "skipped": 0, "refused": 0, "done": 0, "device_s": 0.0,
             "peak_force_n": 0.0, "force_limit_n": 0.0, "max_k": 0.0, "first_refused": None}
        for n, point in enumerate(self.spec.iter_points(), 1):
            s["points"] += 1
            if progress is not None:
                progress(n, total)
            if keys_done and self.key(point) in keys_done:
                s["done"] += 1
                continue
            p = self.plan_point(point)
            if p.refused is not None:
                s["refused"] += 1
                s["first_refused"] = s["first_refused"] or f"point {point.index}: {p.refused}"
            elif p.skipped is not None:
                s["skipped"] += 1
            else:
                s["to_run"] += 1
                s["device_s"] += p.est_s
                s["peak_force_n"] = max(s["peak_force_n"], p.peak_force_n)
                s["force_limit_n"] = max(s["force_limit_n"], p.rig.force_limit_n)
                s["max_k"] = max(s["max_k"], p.max_k)
        s["est_s"] = s["device_s"] + pause * max(s["to_run"] - 1, 0)
        return s


def describe(plan: Plan, done, where, progress=None) -> list[str]:
    """What a person sees before a campaign starts on real hardware (the CLI prints it, the
    window shows it): the points, those already in the table ``where`` (``done``: their keys,
    anything with ``in``), the time, the largest force and stiffness it will command, the
    points whose settings cannot be made, the plant. Every point is planned for it
    (``progress(n, total)``)."""
    s = plan.summary(done, progress)
    c = plan.context
    kind = "simulator" if c.simulated else "real hardware"
    lines = [f"campaign {one_line(plan.spec.name)} on {c.device} ({kind}), rig "
             f"{one_line(repr(c.rig.name))}: {s['points']} points, {s['done']} already in "
             f"{one_line(where)}, {s['to_run']} to run, {s['skipped']} skipped by the pre-check",
             f"  estimated {fmt(s['est_s'] / 60, 3)} min ({fmt(s['device_s'] / 60, 3)} min "
             f"device time, pause {fmt(c.settings.pause_s)} s between points)",
             f"  largest force planned {fmt(s['peak_force_n'])} N (every command clamped at "
             f"{fmt(s['force_limit_n'])} N), stiffest VE {fmt(s['max_k'])} N/m",
             f"  plant m = {fmt(c.plant.m)} kg, b = {fmt(c.plant.b)} N s/m "
             f"({one_line(c.plant_label)})"]
    if s["refused"]:
        lines.insert(1, f"  {s['refused']} points refused (their settings cannot be made; a row "
                        f"each says why), the first {one_line(s['first_refused'])}")
    return lines


def commission_facts(directory, rig_name: str, on_skip=None) -> dict:
    """What the rig's newest successful commissioning in ``directory`` found (``{}``: none):
    its session, Coulomb estimate, counts/rev (if the encoder is wrong) and delay."""
    from labbench.sessions.session_catalogue import last_results

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


def identity(context: Context) -> dict:
    """What a campaign adds to a table (``labbench.sweep.table.claim_identity``)."""
    return {"made_by": "campaign", "kind": "run", "device": context.device, "analysis": None,
            "rig": context.rig.name}


def make_plan(spec: Spec, context: Context) -> Plan:
    """``spec``'s points on ``context``'s device (module doc), its names checked
    (``check_names``); the points are planned as they are asked for."""
    if spec.kind != "run":
        raise UserError(f"{spec.source}: a campaign runs a protocol: [sweep] kind must be run")
    plan = Plan(spec, context)
    check_names(plan)
    return plan


def check_names(plan: Plan) -> None:
    """Refuse a spec whose points the campaign cannot make, before any point: one point of
    every distinct set of names (``Spec.name_samples``: the fixed values, the first of each
    axis, one case of each set of names) is planned, and on a simulator its device opened
    with the point's options and closed. That point's settings, a name nothing knows, a
    simulator's option on real hardware, the commissioning gate: one UserError naming it
    (before, an unknown name in a case stopped the campaign when its first point opened the
    device, and a bad fixed value in a 10^6-point spec was refused after 19.5 s and 719 MB).
    Any other point whose settings cannot be made is a row saying so."""
    from labbench.registry import open_device

    spec, context = plan.spec, plan.context
    seen = set()
    for p in spec.name_samples():
        names = frozenset(p.params)
        if names in seen:
            continue
        seen.add(names)
        where = f"{spec.source}: the point {one_line(p.tags) if p.tags else ''}"
        dev = _device_options(spec, context, route(spec.protocol, p.params), where)
        refused = plan.plan_point(p).refused
        if refused is not None:
            raise UserError(f"{where.rstrip()} ({_shown(p.params)}): {refused}")
        if dev and context.simulated:
            try:
                open_device(context.device, context.rig, **dev).close()
            except UserError as exc:
                if "unknown" in str(exc):
                    raise UserError(f"{spec.source}: {exc}") from None


def _shown(params: dict, n: int = 4) -> str:
    items = [f"{k}={v}" for k, v in params.items()]
    return one_line(", ".join(items[:n]) + (", ..." if len(items) > n else ""))


def _device_options(spec: Spec, context: Context, r: dict, where: str) -> dict:
    """The point's simulator options (seed aside); a name a campaign refuses is a UserError."""
    if DEVICE_DELAY in r["sweep"]:
        raise UserError(f"{where}: {DEVICE_DELAY} sets a sweep simulator's delay; a campaign "
                        "measures the device it runs on (the rig's measured_td_s is its delay)")
    dev = {k: v for k, v in r["device"].items() if k != "seed"}
    if dev and not context.simulated:
        raise UserError(f"{where}: {', '.join(sorted(dev))}: not a setting of protocol "
                        f"{spec.protocol} or of the rig (a simulator's options are for simulators)")
    return dev


def _plan_point(spec: Spec, context: Context, point: Point, tgt: dict) -> PlannedPoint:
    from labbench.protocol import precheck
    from labbench.registry import make_protocol, protocol_class

    where = f"{spec.source}: point {point.index}"
    r = route(spec.protocol, point.params)
    dev = _device_options(spec, context, r, where)
    seed = r["device"].get("seed")
    key = point_key(tgt, point.params, point.tags)
    fields = set(protocol_class(spec.protocol).Config.__dataclass_fields__)
    opts = {k: v for k, v in r["protocol"].items() if k != "sample_time_s"}  # the rig's
    plant_from = None  # the start record's: a plant the point's own settings give says so itself
    if "plant_m_kg" in fields and "plant_m_kg" not in opts and "plant_b" not in opts:
        opts.update(plant_m_kg=context.plant.m, plant_b=context.plant.b)
        plant_from = context.plant_record()
    if "plant_coulomb_n" in fields and "plant_coulomb_n" not in opts and context.coulomb_n:
        opts["plant_coulomb_n"] = context.coulomb_n
    try:
        rig = point_rig(context.rig, r["rig"], where)
        plant = Plant(opts.get("plant_m_kg", context.plant.m), opts.get("plant_b", context.plant.b))
        delay = device_delay.resolve(rig)
        if K_FRACTION in r["sweep"]:
            opts["K"] = _k_from_fraction(spec.protocol, opts, rig, plant, delay.s,
                                         r["sweep"][K_FRACTION])
        protocol = make_protocol(spec.protocol, sample_time_s=rig.sample_time_s, **opts)
    except UserError as exc:
        return PlannedPoint(point, key, spec.protocol, opts, context.rig, {}, None,
                            refused=one_line(exc))
    commissioning.gate(protocol.vetted_ves(plant), rig, context.simulated,
                       context.skip_commissioning)
    pp = PlannedPoint(point, key, spec.protocol, opts, rig,
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
