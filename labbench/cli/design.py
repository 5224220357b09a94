"""``labbench design``: stability, accuracy and force noise of a spring-damper on the rig's
identified device over K, B, w0 and T; the Pareto front of the three; the w0 that maximises
the Z-width (or the accurate band) under a noise limit; a campaign's measurements beside it."""
from __future__ import annotations

import json
import math
import sys

from labbench.cli.main import float_list
from labbench.errors import UserError

NOISE_BAND_DEFAULT = "10,500"


def register(subparsers) -> None:
    from labbench.design.tradeoffs import NOISE_OF, OBJECTIVES

    p = subparsers.add_parser(
        "design", help="the three-way trade-off (stability, accuracy, force noise) of a "
                       "spring-damper on the rig's device, and the w0 to choose",
        description=__doc__)
    p.add_argument("--rig", metavar="FILE", help="rig file (default: the simulated "
                   "Phantom-like rig): sample time, encoder step, delay, a simulator's noise")
    p.add_argument("--out", default="sessions", metavar="DIR",
                   help="where the rig's last chirp-ID and commissioning are looked for "
                        "(default ./sessions)")
    p.add_argument("--plant-from", choices=("last-id", "nominal"), default="last-id",
                   help="the device's m, b (and Coulomb friction): the rig's newest chirp-ID "
                        "in --out, else the rig's nominal model (default last-id)")
    p.add_argument("--plant-m-kg", type=float, metavar="KG", help="device mass, given")
    p.add_argument("--plant-b", type=float, metavar="NS_PER_M", help="device damping, given")
    p.add_argument("--coulomb-n", type=float, metavar="N",
                   help="Coulomb friction, given (default: the chirp-ID's, else the rig's "
                        "last commissioning's, else unknown)")
    p.add_argument("--device-delay-s", type=float, metavar="S",
                   help="the device's delay on the whole command (default: the rig's "
                        "measured_td_s, else 0)")
    p.add_argument("--quantum-m", type=float, metavar="M",
                   help="encoder step at the handle (default: the rig's, 2 pi lever_arm_m / "
                        "counts_per_rev; a simulator's only when it quantises)")
    p.add_argument("--force-noise-n", type=float, metavar="N",
                   help="std of the amplifier's white force noise (default: a simulated rig's "
                        "[sim] force_noise_n, else none)")
    p.add_argument("--simulated", action="store_true",
                   help="the rig is a simulator: its [sim] table says whether the encoder "
                        "quantises and what force noise it adds")
    p.add_argument("--K", type=float_list, default=[50.0], metavar="N_PER_M[,...]",
                   help="virtual stiffness values (default 50)")
    p.add_argument("--B", type=float_list, default=[0.0, 0.5, 1.0, 1.5, 2.0],
                   metavar="NS_PER_M[,...]", help="virtual damping values (default 0,0.5,1,1.5,2)")
    p.add_argument("--w0", type=float_list, default=[60.0, 90.0, 125.0, 180.0, 250.0, 360.0, 500.0],
                   metavar="RAD_S[,...]",
                   help="velocity filter cut-offs (default 60,90,125,180,250,360,500)")
    p.add_argument("--T", type=float_list, metavar="S[,...]",
                   help="loop periods (default: the rig's sample time)")
    p.add_argument("--noise-limit-n", type=float, metavar="N",
                   help="largest acceptable force noise, rms in the felt band (default: none)")
    p.add_argument("--noise-of", choices=NOISE_OF, default="command",
                   help="which noise the limit holds: the loop's command (default; what a "
                        "record shows) or the held force felt, the amplifier's noise included")
    p.add_argument("--band-hz", type=float_list, default=float_list(NOISE_BAND_DEFAULT),
                   metavar="LO,HI", help="the felt band (default 10,500: paper sec. 5)")
    p.add_argument("--at-w", type=float, default=None, metavar="RAD_S",
                   help="frequency of the ED error (default 62.8 rad/s = 10 Hz, the top of "
                        "volitional motion)")
    p.add_argument("--motion-m-s", type=float, metavar="M_S",
                   help="the hand's rms speed, for the quantisation error's colour and "
                        "friction's equivalent damping (default: white quantisation error, "
                        "as for any motion faster than ~half a step per sample; no b_eq)")
    p.add_argument("--excitation-n", type=float, default=None, metavar="N",
                   help="std of the white force that moves the handle, for Coulomb friction's "
                        "noise (default 0.5, the white-noise ETFE's; with --motion-m-s the force "
                        "that moves it at that speed)")
    p.add_argument("--amplitude-m", type=float, default=1e-3, metavar="M",
                   help="oscillation amplitude the friction-aware stability boundary is for: "
                        "oscillations that large decay below it (default 0.001)")
    p.add_argument("--objective", choices=OBJECTIVES, default="zwidth",
                   help="what the recommended w0 maximises: the Z-width under the noise limit "
                        "(default) or the accurate band w_b* at the first --B")
    p.add_argument("--compare", metavar="TABLE", nargs="+",
                   help="campaign tables (design-noise.toml, design-zwidth.toml runs) whose "
                        "measurements to set beside the predictions")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", metavar="FILE", help="write the figure (.png, .svg, .pdf)")
    p.add_argument("--force", action="store_true", help="replace an existing --plot file")
    p.set_defaults(func=run)


def device_of(args):
    """The rig and the ``labbench.design.tradeoffs.Device`` the arguments and the rig's sessions
    describe (``labbench.design.tradeoffs.device_for``, the given values over it)."""
    from dataclasses import replace

    from labbench.model import device_delay
    from labbench.campaign.plan import commission_facts
    from labbench.design.tradeoffs import device_for
    from labbench.rig import load_rig
    from labbench.sessions.session_catalogue import last_identified
    from labbench.model.ve import Plant

    rig = load_rig(args.rig)

    def skipped(path, reason):
        print(f"labbench design: warning: skipped {path}: {reason}", file=sys.stderr)

    if (args.plant_m_kg is None) != (args.plant_b is None):
        raise UserError("give --plant-m-kg and --plant-b together")
    found = last_identified(args.out, rig.name, on_skip=skipped) \
        if args.plant_m_kg is None and args.plant_from == "last-id" else None
    device = device_for(rig, args.simulated, found,
                        commission_facts(args.out, rig.name, on_skip=skipped))
    given, sources = {}, dict(device.sources)
    for key, value, field, check in (
            ("plant", args.plant_m_kg, "plant", None),
            ("coulomb", args.coulomb_n, "coulomb_n", "--coulomb-n"),
            ("latency", args.device_delay_s, "latency", None),
            ("quantum", args.quantum_m, "quantum_m", "--quantum-m"),
            ("force_noise", args.force_noise_n, "force_noise_n", "--force-noise-n")):
        if value is None:
            continue
        if field == "plant":
            value = Plant(args.plant_m_kg, args.plant_b)
        elif field == "latency":
            value = device_delay.checked(args.device_delay_s, "--device-delay-s")
        else:
            value = _nonneg(value, check)
        given[field], sources[key] = value, "given"
    return rig, replace(device, **given, sources=sources)


def _nonneg(v: float, what: str) -> float:
    if not (math.isfinite(v) and v >= 0):
        raise UserError(f"{what} must be a finite number >= 0, got {v:g}")
    return float(v)


def targets_of(args):
    from labbench.design.tradeoffs import ACCURACY_W, EXCITATION_N, Targets

    if len(args.band_hz) != 2:
        raise UserError(f"--band-hz takes two numbers LO,HI, got {len(args.band_hz)}")
    return Targets(noise_limit_n=args.noise_limit_n, noise_of=args.noise_of,
                   band_hz=(args.band_hz[0], args.band_hz[1]),
                   at_w=ACCURACY_W if args.at_w is None else args.at_w, motion_m_s=args.motion_m_s,
                   amplitude_m=args.amplitude_m,
                   excitation_n=EXCITATION_N if args.excitation_n is None else args.excitation_n)


def run(args) -> int:
    from labbench.design.tradeoffs import MODELS, Designer, pareto
    from labbench.jsonutil import json_safe
    from labbench.safe_write import output_path

    if args.plot:
        if _suffix(args.plot) not in ("png", "svg", "pdf"):
            raise UserError(f"figure {args.plot}: use a .png, .svg or .pdf file name")
        output_path(args.plot, force=args.force)  # before the work
    rig, device = device_of(args)
    targets = targets_of(args)
    Ts = args.T or [rig.sample_time_s]
    for name, values in (("--K", args.K), ("--B", args.B), ("--w0", args.w0), ("--T", Ts)):
        if any(not math.isfinite(v) for v in values):
            raise UserError(f"{name} values must be finite numbers")
    n = len(args.K) * len(args.B) * len(args.w0) * len(Ts)
    if n > 5000:
        raise UserError(f"{n} settings: at most 5000 (narrow --K, --B, --w0 or --T)")
    designer = Designer(device, targets)
    points = designer.sweep(args.K, args.B, args.w0, Ts, progress=_progress(n))
    front = pareto(points)
    rec = None
    if len(args.w0) > 1:
        rec = designer.recommend(args.K[0], args.B, args.w0, Ts[0], args.objective,
                                 B=args.B[0])
    check = None
    if args.compare:
        check = _compare(designer, args.compare)
    if args.plot:
        _plot(args, points, rec, targets, check)
    if args.json:
        print(json.dumps(json_safe({
            "device": device.as_dict(), "targets": {
                "noise_limit_n": targets.noise_limit_n, "noise_of": targets.noise_of,
                "band_hz": list(targets.band_hz), "at_w": targets.at_w,
                "motion_m_s": targets.motion_m_s, "amplitude_m": targets.amplitude_m,
                "excitation_n": targets.excitation_n},
            "models": MODELS, "points": [p.as_dict() for p in points],
            "pareto": [points.index(p) for p in front], "recommendation": rec,
            "check": check.as_dict() if check else None})))
    else:
        print("\n".join(_text(device, targets, points, front, rec, args.K[0], Ts[0])))
        if check:
            from labbench.design.checking import table_lines

            print()
            print("\n".join(table_lines(check)))
    if args.plot:
        print(f"wrote {args.plot}")
    return 0


def _progress(n: int):
    if n < 50:
        return None

    def show(i, total):
        if i == total or i % 25 == 0:
            print(f"labbench design: {i}/{total} settings", file=sys.stderr)
    return show


def _compare(designer, tables):
    from labbench.design.checking import check
    from labbench.sweep import table as sweep_tables

    from pathlib import Path

    rows = []
    for t in tables:
        if not Path(t).is_dir():
            raise UserError(f"--compare {t}: not a campaign table (the folder `labbench "
                            "campaign` writes)")
        rows += sweep_tables.read_table(t).to_pylist()
    return check(designer, rows)


def _plot(args, points, rec, targets, check) -> None:
    from labbench.design.charts import check_figure, tradeoff_figure
    from labbench.safe_write import replacing

    fig = check_figure(check) if check else tradeoff_figure(points, rec, targets.noise_limit_n,
                                                           targets.noise_of)
    with replacing(args.plot, force=args.force) as tmp:
        fig.savefig(tmp, dpi=110, format=_suffix(args.plot))


def _suffix(path: str) -> str:
    return path.rsplit(".", 1)[-1].lower() if "." in path else ""


def _text(device, targets, points, front, rec, K0, T0) -> list[str]:
    from labbench.readout.numfmt import fmt

    d = device
    s = d.sources
    lines = [
        f"device: m = {fmt(d.plant.m)} kg, b = {fmt(d.plant.b)} N s/m ({s['plant']}); "
        f"delay {fmt(1e3 * d.latency)} ms ({s['latency']})",
        f"  encoder step {fmt(1e6 * d.quantum_m)} um ({s['quantum']}); amplifier noise "
        f"{fmt(1e3 * d.force_noise_n)} mN ({s['force_noise']}); Coulomb friction "
        f"{fmt(d.coulomb_n)} N ({s['coulomb']})",
        f"targets: {_limit_text(targets)}"
        f" in {fmt(targets.band_hz[0])}-{fmt(targets.band_hz[1])} Hz; ED error at "
        f"{fmt(targets.at_w)} rad/s",
        "models: K_max exact sampled loop; K_pass Colgate & Schenkel sampled-data passivity; "
        f"K_q Abbott & Okamura 2 fc/Delta; K_fric stable for {fmt(1e3 * targets.amplitude_m)} mm "
        "oscillations with friction (describing function); w_s*, w_b*, rendered B, ED error "
        "(sampled: as an "
        "ETFE measures; paper: eq. 2, as felt) exact sampled unless said; noise "
        "labbench.model.noise (command = recorded, felt = held force + amplifier)"
        + (f" with Coulomb friction {fmt(d.coulomb_n)} N under {_motion(targets)}: its "
           "equivalent damper (Booton) and its remnant's noise (arcsine law)" if d.coulomb_n
           else ""),
        "",
        f"{'K':>6} {'B':>5} {'w0':>6} {'T ms':>5} | {'K_max':>7} {'margin':>6} {'K_pass':>7} "
        f"{'K_q':>6} {'K_fric':>7} | {'w_s*':>6} {'w_b*':>6} {'B rend':>6} {'EDerr s':>7} "
        f"{'EDerr p':>7} | {'cmd mN':>6} {'felt mN':>7} | ok  P",
    ]
    for p in points:
        mark = "*" if p in front else ""
        ok = "yes" if p.within_limit else ("UNSTABLE" if not p.stable else "no")
        lines.append(
            f"{fmt(p.K):>6} {fmt(p.B):>5} {fmt(p.w0):>6} {fmt(1e3 * p.T):>5} | "
            f"{fmt(p.k_max):>7} {fmt(p.margin, 3):>6} {fmt(p.k_passive):>7} "
            f"{fmt(p.k_quantised):>6} {fmt(p.k_friction):>7} | {fmt(p.ws_star):>6} "
            f"{fmt(p.wb_star):>6} {fmt(p.rendered_B):>6} {_pct(p.ed_error_sampled):>7} {_pct(p.ed_error_paper):>7} | "
            f"{_mn(p.noise_command):>6} {_mn(p.noise_felt):>7} | {ok} {mark}")
    lines.append(f"P: on the Pareto front of margin, w_b* and felt noise ({len(front)} of "
                 f"{len(points)} settings)")
    if d.coulomb_n:
        lines.append("; ".join(_friction_notes(points)))
    if d.coulomb_n and targets.motion_m_s:
        lines.append(f"friction adds {fmt(points[0].b_friction)} N s/m of damping to what is "
                     f"rendered at a hand speed of {fmt(targets.motion_m_s)} m/s rms")
    if rec is not None:
        lines.append("")
        what = ("Z-width under the noise limit (area under K_max(B) up to the noise-limited B)"
                if rec["objective"] == "zwidth" else "w_b* under the noise limit")
        lines.append(f"w0 for the {what}, at K = {fmt(K0)} N/m, T = {fmt(T0)} s:")
        for r in rec["by_w0"]:
            extra = (f", B up to {fmt(r['b_limit'])} N s/m" if "b_limit" in r else "")
            lines.append(f"  w0 {fmt(r['w0']):>6} rad/s: {fmt(r['value'])}{extra}")
        lines.append(f"recommended w0 = {fmt(rec['w0'])} rad/s" if rec["w0"] is not None
                     else "no w0 meets the noise limit")
    return lines


def _friction_notes(points) -> list[str]:
    """What friction does to the noise of these points, in a few words."""
    from labbench.model.noise import STICK_SHARE_MAX
    from labbench.readout.numfmt import fmt

    parts = [p.noise_friction for p in points if p.noise_friction is not None]
    shares = [p.stick_share for p in points if p.stick_share is not None]
    notes = []
    if parts:
        notes.append(f"friction's part of the felt noise {fmt(1e3 * min(parts), 3)}-"
                     f"{fmt(1e3 * max(parts), 3)} mN")
    if shares:
        notes.append(f"it sticks the handle at up to {100 * max(shares):.2g} % of reversals"
                     + (f" (above {100 * STICK_SHARE_MAX:g} %: the Gaussian velocity it assumes "
                        "fails, its noise a rough guess)" if max(shares) > STICK_SHARE_MAX else ""))
    if any(p.stable and p.noise_command is None for p in points):
        notes.append("'-' noise: friction holds the handle under this motion")
    return notes


def _motion(targets) -> str:
    from labbench.readout.numfmt import fmt

    return (f"the white force that moves the handle at {fmt(targets.motion_m_s)} m/s rms"
            if targets.motion_m_s else f"{fmt(targets.excitation_n)} N of white excitation")


def _limit_text(targets) -> str:
    from labbench.readout.numfmt import fmt

    if targets.noise_limit_n is None:
        return "no noise limit"
    return f"{targets.noise_of} noise within {fmt(1e3 * targets.noise_limit_n)} mN rms"


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.1f}%"


def _mn(v) -> str:
    from labbench.readout.numfmt import fmt

    return "-" if v is None else fmt(1e3 * v, 3)
