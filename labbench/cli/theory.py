"""``labbench theory``: closed-loop impedance, effective impedances and stability of a VE."""
from __future__ import annotations

import json
import math

import numpy as np

from labbench.model import predictions
from labbench.readout import bandwidth_text
from labbench.model import linear
from labbench.cli.main import float_list
from labbench.readout.numfmt import fmt
from labbench.jsonutil import json_safe
from labbench.model.effective import effective_impedances
from labbench.errors import UserError
from labbench.model.ve import Plant, VirtualEnvironment

KINDS = ("spring", "damper", "spring-damper")
# which of --K, --B, --w0 each VE uses
USES = {"spring": ("K",), "damper": ("B", "w0"), "spring-damper": ("K", "B", "w0")}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "theory",
        help="closed-loop impedance of a virtual environment (paper or exact sampled model)",
        description=__doc__)
    p.add_argument("--ve", required=True, choices=KINDS, help="virtual environment")
    p.add_argument("--m", type=float, required=True, metavar="KG", help="device mass")
    p.add_argument("--b", type=float, required=True, metavar="NS_PER_M", help="device damping")
    p.add_argument("--K", type=float, metavar="N_PER_M", help="virtual stiffness")
    p.add_argument("--B", type=float, metavar="NS_PER_M", help="virtual damping")
    p.add_argument("--w0", type=float, metavar="RAD_S",
                   help="velocity low-pass cut-off (default: none)")
    p.add_argument("--T", type=float, default=0.001, metavar="S",
                   help="sample time (default 0.001)")
    p.add_argument("--td", type=float_list, default=[0.0], metavar="S[,S...]",
                   help="external delay; a list overlays one curve per value with --plot")
    p.add_argument("--device-delay-s", type=float, default=0.0, metavar="S",
                   help="the device's own delay on the whole command (a drive that applies "
                        "the torque at the next SYNC: one sample time), beyond td; "
                        "fractions of a sample allowed (default 0)")
    p.add_argument("--model", choices=linear.MODELS, default="paper",
                   help="paper: eq. 2 with delay T/2 + td; sampled: exact sampled-data loop")
    p.add_argument("--w", type=float_list, metavar="W1,W2,...",
                   help="frequencies (rad/s), up to the Nyquist frequency pi/T (default: a log "
                        "grid, 31 points in the table, 200 with --json or --plot)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", metavar="FILE", help="write a paper-style figure (.png, .svg, .pdf)")
    p.add_argument("--force", action="store_true", help="replace an existing --plot file")
    p.set_defaults(func=run)


def run(args) -> int:
    from labbench.safe_write import output_path

    if args.plot:
        output_path(args.plot, force=args.force)  # before the work
    from labbench.model import device_delay

    plant = Plant(args.m, args.b)
    latency = device_delay.checked(args.device_delay_s, "--device-delay-s")
    ves = [_ve(args, td) for td in args.td]
    if len(ves) > 1 and (args.json or not args.plot):
        raise UserError("several --td values need --plot (and no --json); give one value otherwise")
    if args.w is not None and any(not (w > 0) or math.isinf(w) for w in args.w):
        raise UserError("--w frequencies must be positive finite rad/s")
    nyquist = math.pi / args.T if args.T > 0 else math.inf
    above = [w for w in args.w or () if w > nyquist * (1 + 1e-12)]
    if above:
        raise UserError(f"--w {fmt(max(above), 6)} rad/s is above the Nyquist frequency pi/T = "
                        f"{fmt(nyquist, 6)} rad/s of T = {fmt(args.T)} s: a sampled loop "
                        "has no response of its own there (it would be an alias)")
    if args.model == "sampled":
        for ve in ves:
            ve.delay_samples  # one clear error when td is not whole samples
    grid_points = 200 if (args.json or args.plot) else 31
    if args.w is not None:
        w = np.asarray(args.w, float)
    else:
        w = default_grid(plant, ves[0], grid_points)
    summaries = [summary(plant, ve, w, args.model, latency) for ve in ves]

    if args.plot:
        _plot(args, plant, ves, w, latency)
    if args.json:
        out = summaries[0]
        out["w"] = list(args.w) if args.w is not None else out["w"]
        print(json.dumps(json_safe(out)))
    elif len(ves) == 1:
        print(table(summaries[0]))
    else:
        for s in summaries:
            print(_headline(s))
    if args.plot:
        print(f"wrote {args.plot}")
    return 0


def _ve(args, td: float) -> VirtualEnvironment:
    uses = USES[args.ve]
    given = {name: getattr(args, name) for name in ("K", "B", "w0")
             if getattr(args, name) is not None}
    stray = [f"--{name}" for name in given if name not in uses]
    if stray:
        raise UserError(f"{', '.join(stray)} does not apply to --ve {args.ve}")
    for name in ("K", "B"):
        if name in uses and not (given.get(name, 0.0) > 0):
            raise UserError(f"--ve {args.ve} needs --{name} > 0")
    return VirtualEnvironment(kind=args.ve, K=given.get("K", 0.0), B=given.get("B", 0.0),
                              w0=given.get("w0", math.inf), T=args.T, td=td)


def default_grid(plant: Plant, ve: VirtualEnvironment, n: int) -> np.ndarray:
    """Log-spaced w from a decade below the slowest corner (at most 1 rad/s) to
    a decade above w0 (at least 1000 rad/s), capped at the Nyquist rate pi/T."""
    corners = [r for r in (linear.predicted_ws_star(plant, ve), linear.predicted_wb_star(ve)) if r]
    lo = min([1.0] + [0.1 * r for r in corners])
    hi = min(max([1000.0] + [10 * r for r in corners]), math.pi / ve.T)
    return np.logspace(math.log10(lo), math.log10(hi), n)


def summary(plant: Plant, ve: VirtualEnvironment, w: np.ndarray, model: str,
            latency: float = 0.0) -> dict:
    """Everything the CLI reports for one VE: the contract keys plus context. ``latency``:
    the device's own delay [s] on the whole command (``labbench.model.device_delay``)."""
    Z = linear.theory_curve(plant, ve, w, model, latency)
    eff = effective_impedances(w, Z)
    whole = linear.whole_samples(ve)
    st = linear.stability(plant, ve, latency) if whole else None
    kmax = linear.k_max(plant, ve, latency=latency) if whole else None
    kapp = linear.k_max_approx(plant, ve, latency)
    bw = predictions.bandwidths(plant, ve, latency)
    return {
        "model": model,
        # which model each field is of: Z and what is read off it follow --model; stability
        # and K_max are always the exact sampled loop's; K_max_approx the paper's formula
        "model_of": {**dict.fromkeys(("Z_re", "Z_im", "ES", "ED", "EM"), model),
                     **dict.fromkeys(("stable", "spectral_radius", "stability_margin", "K_max"),
                                     "sampled"),
                     "K_max_approx": "paper",
                     **dict.fromkeys(("ws_star", "wb_star"), bw.model)},
        "ve": ve.as_dict(),
        "plant": {"m": plant.m, "b": plant.b},
        "device_delay_s": latency,
        "w": w,
        "Z_re": Z.real,
        "Z_im": Z.imag,
        "ES": eff.ES,
        "ED": eff.ED,
        "EM": eff.EM,
        # sampled-model stability; null when td is not whole samples (no sampled model)
        "stable": None if st is None else st.stable,
        "spectral_radius": None if st is None else st.spectral_radius,
        "stability_margin": None if st is None else st.margin,  # 1 - spectral radius, exactly
        "K_max": kmax,
        "K_max_approx": kapp,
        "K_max_margin": (kmax / kapp - 1) if kmax is not None and kapp else None,
        # read off the exact sampled model with the device delay (labbench.model.predictions),
        # the paper's closed forms beside them
        "ws_star": bw.ws_star,
        "wb_star": bw.wb_star,
        "ws_star_eq5": bw.ws_star_eq5,
        "wb_star_w0": bw.wb_star_w0,
        "bandwidths_model": bw.model,
        "delay_effects": linear.delay_effects(plant, ve, latency),
    }




def _headline(s: dict) -> str:
    ve = s["ve"]
    if s["stable"] is None:
        stab = "sampled loop: n/a (td not whole samples)"
    else:
        verdict = "stable" if s["stable"] else "UNSTABLE"
        margin = s["stability_margin"]  # near 1 the radius as 1 -/+ the margin: never "1.000000"
        radius = (f"{s['spectral_radius']:.6f}" if abs(margin) >= 5e-7 else
                  f"1 {'-' if margin > 0 else '+'} {abs(margin):.2g}")
        stab = f"sampled loop {verdict} (spectral radius {radius})"
    line = f"td = {ve['td']:g} s: {stab}"
    if s["K_max_approx"] is not None:
        line += (f"; K_max {fmt(s['K_max'])} N/m sampled (paper approx "
                 f"{fmt(s['K_max_approx'])})")
    de = s["delay_effects"]
    if "ED_drop_paper" in de:
        line += (f"; low-w ED drop {fmt(de['ED_drop_paper'])} paper, {fmt(de['ED_drop_sampled'])}"
                 f" sampled vs K(T/2+td) = {de['K_tau']:.4g} N s/m")
    if "EM_drop_paper" in de:
        line += (f"; low-w EM drop {fmt(de['EM_drop_paper'])} paper, {fmt(de['EM_drop_sampled'])}"
                 f" sampled vs B(T/2+td) = {de['B_tau']:.4g} kg")
    return line


def table(s: dict) -> str:
    ve, pl = s["ve"], s["plant"]
    bw = predictions.bandwidths(Plant(pl["m"], pl["b"]), VirtualEnvironment.from_dict(ve),
                                s["device_delay_s"])
    head = [
        f"{ve['kind']} VE, {s['model']} model: m = {pl['m']:g} kg, b = {pl['b']:g} N s/m, "
        + "".join(f"{name} = {fmt(ve[name], 6)} {unit}, " for name, unit in
                  (("K", "N/m"), ("B", "N s/m"), ("w0", "rad/s")) if name in USES[ve["kind"]])
        + f"T = {ve['T']:g} s",
        _headline(s),
        "; ".join(f"{predictions.SYMBOLS[k]}: {bandwidth_text.predicted_text(k, bw)}" for k in ("ws", "wb")),
        "",
        f"{'w rad/s':>10} {'|Z| dB':>8} {'phase':>8} {'Re Z':>10} {'Im Z':>10} "
        f"{'ES N/m':>10} {'ED Ns/m':>10} {'EM kg':>10}",
    ]
    Z = np.asarray(s["Z_re"]) + 1j * np.asarray(s["Z_im"])
    phase = np.degrees(np.unwrap(np.angle(Z)))
    # ES where Im Z < 0, EM where Im Z > 0 (paper Figure 2); the JSON keeps both signed
    rows = [
        f"{w:10.4g} {20 * np.log10(abs(z)):8.2f} {ph:8.2f} {z.real:10.4g} {z.imag:10.4g} "
        f"{fmt(es if z.imag < 0 else None):>10} {ed:10.4g} {fmt(em if z.imag > 0 else None):>10}"
        for w, z, ph, es, ed, em in zip(s["w"], Z, phase, s["ES"], s["ED"], s["EM"])
    ]
    return "\n".join(head + rows)


def _plot(args, plant: Plant, ves: list[VirtualEnvironment], w: np.ndarray,
          latency: float = 0.0) -> None:
    from labbench.readout.figures import Curve, paper_figure

    dev = f" + device {1e3 * latency:g} ms" if latency else ""
    curves = [Curve(label=f"td = {1e3 * ve.td:g} ms (T/2 + td{dev} = {1e3 * (ve.delay + latency):g} ms)",
                    w=w, Z=linear.theory_curve(plant, ve, w, args.model, latency)) for ve in ves]
    ve = ves[0]
    marks = {"ws*": linear.predicted_ws_star(plant, ve), "wb*": linear.predicted_wb_star(ve)}
    gains = ", ".join(f"{n} = {getattr(ve, n):g}" for n in ("K", "B") if n in USES[ve.kind])
    if "w0" in USES[ve.kind]:
        gains += f", w0 = {ve.w0:g}"
    title = (f"{ve.kind} VE ({args.model} model): m = {plant.m:g} kg, b = {plant.b:g} N s/m, "
             f"{gains}, T = {ve.T:g} s")
    paper_figure(curves, args.plot, title=title, marks={k: v for k, v in marks.items() if v},
                 force=args.force)
