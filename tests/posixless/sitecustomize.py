"""Make this interpreter look like a Windows Python to labbench: the POSIX-only names gone.

Put on PYTHONPATH with LABBENCH_POSIXLESS=1 (``tests/test_platform_posixless.py``): Python
imports this at start-up, before any labbench module, in every process (the GUI's spawned
acquisition process too). Removed: what a Windows Python lacks and labbench could touch
(signal.SIGHUP, os.sched_*/SCHED_*, os.openpty/ttyname, os.O_NONBLOCK/O_CLOEXEC; the
modules termios, tty, pty, fcntl, resource). pyserial is imported first: on Windows it has
a backend of its own (serialwin32), here its POSIX one keeps the references it took.
"""
import os

if os.environ.get("LABBENCH_POSIXLESS") == "1":
    import signal
    import sys

    import serial  # noqa: F401 - before termios/fcntl go (see above)

    for _name in ("SIGHUP",):
        if hasattr(signal, _name):
            delattr(signal, _name)
    for _name in [n for n in dir(os) if n.startswith(("sched_", "SCHED_"))] + [
            "openpty", "ttyname", "O_NONBLOCK", "O_CLOEXEC"]:
        if hasattr(os, _name):
            delattr(os, _name)
    for _name in ("termios", "tty", "pty", "fcntl", "resource"):
        sys.modules[_name] = None  # import raises ModuleNotFoundError, as on Windows
