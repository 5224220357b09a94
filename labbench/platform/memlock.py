"""Locking the process's pages in RAM (``mlockall``, POSIX; Windows locks only ranges)."""
from __future__ import annotations

import ctypes
import ctypes.util
import os

from labbench.platform import is_windows

_MCL_CURRENT, _MCL_FUTURE, _MCL_ONFAULT = 1, 2, 4


def available() -> bool:
    """Windows has VirtualLock of given ranges within the working set, not a whole-process lock."""
    return not is_windows()


def _libc():
    return ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)


def lock_all() -> str | None:
    """Lock current and future pages (as they fault in, where the kernel can); None or the error."""
    try:
        libc = _libc()
        call = libc.mlockall
    except (OSError, AttributeError) as exc:
        return f"no mlockall in the C library ({exc})"
    err = 0
    for flags in (_MCL_CURRENT | _MCL_FUTURE | _MCL_ONFAULT, _MCL_CURRENT | _MCL_FUTURE):
        if call(flags) == 0:
            return None
        err = ctypes.get_errno()
        if err != 22:  # EINVAL: no MCL_ONFAULT before Linux 4.4, try without
            return os.strerror(err)
    return os.strerror(err)


def unlock_all() -> None:
    _libc().munlockall()
