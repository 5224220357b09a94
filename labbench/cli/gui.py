"""``labbench gui``: the desktop application (Qt is imported only when the command runs)."""
from __future__ import annotations

import importlib.util
import os
from pathlib import Path

from labbench.errors import UserError, missing_extra

DEFAULT_SESSIONS = "sessions"


def register(subparsers) -> None:
    p = subparsers.add_parser("gui", help="open the desktop application (simulated rig by default)")
    p.add_argument("--rig", metavar="FILE", help="rig file (TOML); a [canopen] or [serial] table "
                   "selects that driver, default: the last one used, else the simulated rig")
    p.add_argument("--sessions", metavar="DIR", default=None,
                   help=f"folder for recorded sessions (default: the last one used, else "
                        f"./{DEFAULT_SESSIONS})")
    p.add_argument("--settings", metavar="FILE.ini",
                   help="where the window keeps its state (default: the user's labbench settings)")
    p.add_argument("--demo", action="store_true", help="run a short simulated ETFE at once")
    p.add_argument("--screenshot", metavar="FILE.png",
                   help="save a screenshot once the result is visible, then exit "
                        "(with --demo: after the live estimate of the whole run shows)")
    p.add_argument("--timeout", type=float, default=180.0, metavar="S",
                   help="with --screenshot: give up after S seconds (exit 1)")
    p.add_argument("--skip-commissioning", action="store_true",
                   help="render a spring or damper on real hardware before the rig passed "
                        "`labbench run commission` (for people who know their rig)")
    p.set_defaults(func=run, own_signals=True)  # Qt's loop; its acquisition process has its own


def run(args) -> int:
    from labbench.rig import load_rig

    for package in ("PySide6", "pyqtgraph"):  # before any setting: say what to install
        if importlib.util.find_spec(package) is None:
            raise missing_extra(package, "gui", "labbench gui")

    from labbench.gui.settings import open_settings, remembered_paths

    shot = Path(args.screenshot) if args.screenshot else None
    # a screenshot run shows the default layout (reproducible docs), and remembers nothing
    settings = open_settings(args.settings) if shot is None or args.settings else None
    rig_path, sessions_dir = ((args.rig, args.sessions or DEFAULT_SESSIONS) if settings is None
                              else remembered_paths(settings, args.rig, args.sessions,
                                                    DEFAULT_SESSIONS))
    rig = load_rig(rig_path)
    if shot is not None and shot.suffix.lower() != ".png":
        raise UserError(f"--screenshot must name a .png file, got {shot}")
    headless = not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
                    or os.environ.get("QT_QPA_PLATFORM"))
    if headless and shot is None:
        raise UserError("no display found (DISPLAY unset); run under a desktop, or use --screenshot")
    if headless:
        os.environ["QT_QPA_PLATFORM"] = "offscreen"  # renders without a display
    else:
        check_x11_plugin()
    sessions = Path(sessions_dir)
    try:
        sessions.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"cannot use session folder {sessions}: {exc}") from None

    from labbench.gui.app import run_app

    from labbench.readout.units import SI

    # --units given: the window starts with them (else with the ones it remembers)
    units = None if getattr(args, "units", SI) is SI else args.units
    return run_app(rig, sessions, demo=args.demo, screenshot=shot, timeout_s=args.timeout,
                   settings=settings, units=units, skip_commissioning=args.skip_commissioning)


# what Qt's X11 plugin needs beyond a desktop's usual libraries (Qt 6.5 and later: xcb-cursor),
# as Debian and Ubuntu package them; a fresh Ubuntu desktop lacks the first
XCB_PACKAGES = "libxcb-cursor0 libxcb-icccm4 libxcb-keysyms1 libxcb-image0 libxcb-render-util0 " \
               "libxcb-shape0 libxcb-xkb1 libxkbcommon-x11-0"


def check_x11_plugin() -> None:
    """One line naming the missing library where Qt's X11 plugin cannot load: Qt itself aborts
    the process with "could not load the Qt platform plugin xcb" and no name."""
    import ctypes

    if os.environ.get("QT_QPA_PLATFORM", "xcb") != "xcb" or not os.environ.get("DISPLAY"):
        return
    spec = importlib.util.find_spec("PySide6")
    plugin = Path(spec.origin).parent / "Qt" / "plugins" / "platforms" / "libqxcb.so"
    if not plugin.is_file():
        return  # another build of Qt: let it say for itself
    try:
        ctypes.CDLL(str(plugin))
    except OSError as exc:
        missing = str(exc).split(":")[0].strip()
        if "cannot open shared object file" in str(exc):
            raise UserError(f"Qt's X11 plugin cannot load: {missing} is missing (Debian/Ubuntu: "
                            f"sudo apt install {XCB_PACKAGES})") from None

