"""The errors labbench raises on purpose, so callers can tell a bad setting from a dead bus.

``LabbenchError`` is the root. The CLI prints any of them as one line; a
``UserError`` exits 2, a device error exits 1.
"""


class LabbenchError(Exception):
    """Root of every error labbench raises on purpose (one clear line, no traceback)."""


class UserError(LabbenchError, ValueError):
    """Bad input from a person (argument, file, configuration)."""


class UnstableVEError(UserError):
    """A virtual environment the exact sampled model calls unstable on this plant."""


class SessionFormatError(UserError):
    """A file that is not a readable labbench session (or whose content is hostile)."""


class MissingExtraError(UserError):
    """A feature needs an optional package that is not installed (the message says which)."""


class RecordingError(LabbenchError):
    """A session could not be written on (full disk, size limit, permission, read-only): the
    message says what was kept. The run stops (the device first) and fails."""


class Cancelled(LabbenchError):
    """An analysis stopped because its cancel event was set (``labbench.analysis.progress``);
    the CLI treats it as an interrupt."""


class DeviceError(LabbenchError):
    """A device did not do what it was asked: root of the device errors."""


class DeviceConnectionError(DeviceError):
    """The bus, port or peer cannot be reached, or stopped answering."""


class DeviceFault(DeviceError, RuntimeError):
    """The device reported or showed a fault; force is already zero when raised."""


def missing_extra(package: str, extra: str, feature: str) -> MissingExtraError:
    """The one-line error for an optional package that is not installed."""
    return MissingExtraError(f"{feature} needs {package}: pip install 'haptic-labbench[{extra}]'")


def nearest_hint(name, known) -> str:
    """``did you mean 'name'?`` for the closest of ``known`` (difflib), else the list."""
    import difflib

    known = sorted(str(k) for k in known)
    close = difflib.get_close_matches(str(name), known, n=1, cutoff=0.6)
    return f"did you mean {close[0]!r}?" if close else f"known: {', '.join(known)}"


def unknown_name(what: str, name, known) -> UserError:
    """``unknown <what> 'nmae'; did you mean 'name'?``, else the list of known names."""
    return UserError(f"unknown {what} {str(name)!r}; {nearest_hint(name, known)}")
