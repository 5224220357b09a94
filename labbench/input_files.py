"""Input files are opened only when they are regular files, and read within a size bound.

A FIFO given as a rig file would block ``open`` for ever, ``/dev/zero`` never
ends, and a directory or a multi-gigabyte file is a mistake to say so about,
not to read. ``O_NONBLOCK`` makes the open itself return at once for a FIFO;
``fstat`` on the open descriptor (not the name, which may change meanwhile)
then decides. Windows has neither flag (nor FIFOs that block an open): 0 there.
"""
from __future__ import annotations

import os
import stat
from pathlib import Path

from labbench.errors import UserError

_NONBLOCK = getattr(os, "O_NONBLOCK", 0)
_FLAGS = os.O_RDONLY | _NONBLOCK | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)


def open_regular(path, what: str, max_bytes: int | None = None):
    """``path`` opened for binary reading, or one UserError naming ``what`` and the problem."""
    p = Path(path)
    try:
        fd = os.open(p, _FLAGS)
    except FileNotFoundError:
        raise UserError(f"{what} not found: {p}") from None
    except (OSError, ValueError) as exc:
        raise UserError(f"cannot read {what} {p}: {getattr(exc, 'strerror', None) or exc}") from None
    try:
        st = os.fstat(fd)
        if stat.S_ISDIR(st.st_mode):
            raise UserError(f"{what} {p} is a directory, not a file")
        if not stat.S_ISREG(st.st_mode):
            raise UserError(f"{what} {p} is not a regular file (a pipe or device is not read)")
        if max_bytes is not None and st.st_size > max_bytes:
            raise UserError(f"{what} {p} is {st.st_size} bytes; at most {max_bytes} are read")
        if _NONBLOCK:
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_text(path, what: str, max_bytes: int) -> str:
    """The whole of a small UTF-8 text file (rig files), within ``max_bytes``."""
    with open_regular(path, what, max_bytes) as f:
        try:
            data = f.read(max_bytes + 1)  # the file may have grown since fstat
        except OSError as exc:
            raise UserError(f"cannot read {what} {path}: {exc.strerror}") from None
    if len(data) > max_bytes:
        raise UserError(f"{what} {path} is longer than {max_bytes} bytes")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UserError(f"{what} {path} is not UTF-8 text (byte {exc.start})") from None
