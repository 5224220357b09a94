"""``labbench export SESSION --hdf5 FILE | --csv FILE``: session to HDF5 or analysis CSV."""
from __future__ import annotations


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "export", help="write a session as HDF5 or as analysis CSV",
        description="Write a recorded session as HDF5 (h5py, MATLAB) or as CSV in the "
                    "analysis format (t, force, position, ...).")
    p.add_argument("session", help="session file (.lbsession)")
    out = p.add_mutually_exclusive_group(required=True)
    out.add_argument("--hdf5", metavar="FILE", help="HDF5 output file")
    out.add_argument("--csv", metavar="FILE", help="CSV output file")
    p.set_defaults(func=run)


def run(args) -> int:
    from labbench.export import export_csv, export_hdf5

    path = export_hdf5(args.session, args.hdf5) if args.hdf5 else export_csv(args.session, args.csv)
    print(path)
    return 0
