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
    p.add_argument("--force", action="store_true", help="replace an existing output file (never one of the inputs)")
    p.set_defaults(func=run)


def run(args) -> int:
    from labbench.cli.progress import warner
    from labbench.sessions.export import export_csv, export_hdf5

    export = export_hdf5 if args.hdf5 else export_csv
    path = export(args.session, args.hdf5 or args.csv, force=args.force, warn=warner("export"))
    print(path)
    return 0
