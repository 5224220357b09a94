"""``labbench analyze``: identify the device (id) or the closed-loop impedance (etfe) from a record.

FILE is a CSV (``# key=value`` metadata lines, a header naming t, force,
position) or a recorded labbench session.
"""
from __future__ import annotations

import json

import numpy as np

from labbench.cli.progress import warner
from labbench.jsonutil import json_safe



def register(subparsers) -> None:
    p = subparsers.add_parser("analyze", help="identification and ETFE of recorded force/position",
                              description=__doc__)
    sub = p.add_subparsers(dest="analysis", required=True, parser_class=type(p))
    from labbench.analysis.etfe import DEFAULT_ESTIMATOR, ESTIMATORS
    from labbench.analysis.identify import HOLDS, METHODS, MODEL_CHOICES, SOLVERS

    q = sub.add_parser("id", help="fit f = m x'' + b x' [+ Fc sign(x')] [+ f0]",
                       description="Identify mass, damping (and friction, offset) with 95 % intervals.")
    q.add_argument("file", metavar="FILE", help="a CSV record (# key=value lines, then t, force, position) or a recorded session")
    q.add_argument("--model", choices=MODEL_CHOICES, default="auto",
                   help="mb, mbc (+Coulomb), mbco (+offset), auto (blocked cross-validation; default)")
    q.add_argument("--method", choices=METHODS, default="l2", help="l2 least squares or l1 (exact LAD)")
    q.add_argument("--solver", choices=SOLVERS, default="fast",
                   help="l1 solver: fast (exact simplex steps, default) or cvxpy (a cross-check, "
                        "about 10x slower)")
    q.add_argument("--cutoff", type=float, metavar="HZ",
                   help="derivative low-pass cut-off (default: 3x the band of the force)")
    q.add_argument("--force-hold", choices=HOLDS, default=None,
                   help="how the force reached the plant: zoh (held over each sample, a commanded "
                        "force) or sample (sampled with the position, a force sensor); default: the "
                        "metadata, else chosen by cross-validation")
    q.add_argument("--json", action="store_true", help="print one JSON object")
    _strict_option(q)
    q.set_defaults(func=run_id)

    e = sub.add_parser("etfe", help="closed-loop impedance Z = F/(jw X) and effective impedances",
                       description="Empirical transfer-function estimate with coherence and a 95 % band.")
    e.add_argument("file", metavar="FILE", help="a CSV record (# key=value lines, then t, force, position) or a recorded session")
    e.add_argument("--estimator", choices=ESTIMATORS, default=DEFAULT_ESTIMATOR,
                   help=f"how Z is estimated (docs/analysis.md; paper: the paper's method "
                        f"exactly); default {DEFAULT_ESTIMATOR}")
    e.add_argument("--window", type=int, default=200, metavar="N",
                   help="Hamming window length in bins for --estimator paper (default 200)")
    e.add_argument("--m", type=float, metavar="KG", help="device mass for the theory overlay")
    e.add_argument("--b", type=float, metavar="NS_PER_M", help="device damping for the theory overlay")
    e.add_argument("--coulomb", type=float, metavar="N",
                   help="device Coulomb friction for the friction-aware theory (default: the "
                        "record's metadata coulomb_n, else estimated from the record)")
    e.add_argument("--fit", action="store_true",
                   help="fit the exact sampled closed-loop model of the metadata's VE to Z: plant m, b, "
                        "the device latency td and the VE-path delay tv (fractions of a sample; which "
                        "delays act chosen by cross-validation), with 95 %% intervals and a verdict")
    e.add_argument("--fit-ve", action="store_true",
                   help="with --fit: also fit the rendered K and B")
    e.add_argument("--band", nargs=2, type=float, metavar=("LO", "HI"),
                   help="the band [rad/s] the verdict, the deviation from the theory and the rendered "
                        "K, B speak of (default 2-100 rad/s, where the accuracy targets hold)")
    e.add_argument("--json", action="store_true", help="print one JSON object")
    e.add_argument("--plot", metavar="FILE", help="paper-style figure (.png, .svg, .pdf)")
    e.add_argument("--csv", metavar="FILE", help="the frequency response as CSV: w in rad/s and "
                   "Hz, Z, its 95 %% radius, coherence, ES, ED, EM (and the theory's Z)")
    e.add_argument("--force", action="store_true", help="replace an existing output file (never one of the inputs)")
    _strict_option(e)
    e.set_defaults(func=run_etfe)


def _strict_option(p) -> None:
    from labbench.readout.verdict import STRICT_EXIT

    p.add_argument("--strict", action="store_true",
                   help=f"exit {STRICT_EXIT} when a result's verdict is failed (for scripts)")


def _verdicts(d: dict) -> list:
    """The verdicts of a result dict: its own and a nested loop fit's (by path)."""
    from labbench.readout.verdict import from_dict

    return [from_dict(d.get("verdict")), from_dict((d.get("fit") or {}).get("verdict"))]


def _exit(d: dict, args) -> int:
    from labbench.readout.verdict import strict_exit

    return strict_exit(_verdicts(d), args.strict)


def run_id(args) -> int:
    from labbench.analysis.dataio import load_recording
    from labbench.session_api import identify_recording


    ident = identify_recording(load_recording(args.file, warner("analyze")), model=args.model,
                               method=args.method,
                               cutoff_hz=args.cutoff, solver=args.solver, force_hold=args.force_hold)
    d, read = ident.as_dict(), ident.readout
    if args.json:
        print(json.dumps(json_safe(d)))
        return _exit(d, args)
    print(f"{args.file}: model {d['model']} by {d['method']}, {d['n_used']} samples, "
          f"derivative cut-off {d['cutoff_hz']:.3g} Hz; fitted to {d['force_source']}")
    for line in read.text_lines():
        print(f"  {line}")
    print(f"  residual rms {d['rms_residual']:.4g} N, force variance explained {100 * d['explained']:.3f} %")
    hold = d["force_hold"]
    ratio = f", CV loss ratio {hold['loss_ratio']:.3g}" if "loss_ratio" in hold else ""
    print(f"  force_hold: {hold['value']} ({hold['source']}{ratio})")
    print(f"  selection: {d['selection'].get('reason') or d['selection'].get('criterion')}")
    for f in d["flags"]:
        print(f"  flag: {f}")
    return _exit(d, args)


def run_etfe(args) -> int:
    from labbench.analysis.dataio import load_recording
    from labbench.safe_write import output_path
    from labbench.session_api import etfe_recording

    for out in (args.plot, args.csv):
        if out:
            output_path(out, [args.file], args.force)  # before the work

    fr = etfe_recording(load_recording(args.file, warner("analyze")), args.estimator, args.window,
                        m=args.m, b=args.b,
                        fit=args.fit, fit_ve=args.fit_ve,
                        band_rad_s=tuple(args.band) if args.band else None, coulomb_n=args.coulomb)
    d = fr.as_dict(args.units)
    read = fr.readout
    if args.plot:
        fr.plot(args.plot, inputs=[args.file], force=args.force)
    if args.csv:
        fr.to_csv(args.csv, force=args.force)
    if args.json:
        print(json.dumps(json_safe(d)))
    else:
        _print_table(args.file, d, fr.comparison, args.units, read)
    for out in (args.plot, args.csv):
        if out:
            print(f"wrote {out}")
    return _exit(d, args)


def _print_table(path, d, cmp, units, read) -> None:
    """What was found, in the words of ``labbench.readout.wording`` (as ``labbench run`` and the
    report say it), then the table in SI, frequencies in the display unit (``--units Hz``)."""
    f, fu = units.frequency_of, units.frequency
    w = f(np.asarray(d["w"]))
    print(f"{path}: estimator {d['estimator']}, {len(w)} frequencies "
          f"{w[0]:.3g}-{w[-1]:.4g} {fu}")
    for line in read.text_lines(units):
        print(line)
    if cmp is not None:
        print(f"theory: {cmp['model']} model")
    if "fit" in d:
        _print_fit(d["fit"])
    for flag in d["flags"]:
        print(f"flag: {flag}")
    print(f"{('w ' if fu == 'rad/s' else 'f ') + fu:>10} {'Re Z':>10} {'Im Z':>10} {'|dZ| 95%':>10} {'coh':>6} "
          f"{'ES N/m':>10} {'ED Ns/m':>10} {'EM kg':>10}")
    step = max(1, len(w) // 40)
    for i in range(0, len(w), step):
        print(f"{w[i]:10.4g} {d['Z_re'][i]:10.4g} {d['Z_im'][i]:10.4g} {d['Z_err'][i]:10.3g} "
              f"{d['coherence'][i]:6.3f} {d['ES'][i]:10.4g} {d['ED'][i]:10.4g} {d['EM'][i]:10.4g}")


def _print_fit(fit: dict) -> None:
    """What the readout's closed-loop fit row leaves out: where it was fitted, its delays."""
    from labbench.readout.numfmt import fmt_ci

    print(f"closed-loop fit: {fit['n_freq']} frequencies {fit['band_rad_s'][0]:.3g}-"
          f"{fit['band_rad_s'][1]:.4g} rad/s, residual rms {100 * fit['residual_rms']:.2f} % of |Z|, "
          f"chi2/dof {fit['chi2_dof']:.3g}")
    for key, unit in (("K", "N/m"), ("B", "N s/m")):
        if key in fit:
            print(f"  fitted {key} = {fmt_ci(fit[key], *fit['ci95'][key], unit)}")
    print(f"  delays: {fit['selection'].get('reason', fit['delay_model'])}")
    print(f"  VE-path delay tv {1e3 * fit['tv_s']:.4g} ms (metadata td {1e3 * fit['td_meta_s']:g} ms), "
          f"device latency td {1e3 * fit['td_s']:.4g} ms; loop delay {1e3 * fit['loop_delay_s']:.4g} ms")


def _pct(v) -> str:
    return "-" if v is None else f"{100 * v:.2f} %"
