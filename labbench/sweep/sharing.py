"""One sweep table, several sweeps at once (the same spec or others): a lock and claims.

Inside ``NAME.sweep/`` (names starting with ``_`` are skipped by Parquet readers):

* ``_lock``: the table's lock, an exclusive lock on a file that stays. It is held for
  moments: to claim points, to write ``_spec.json``, to merge the parts, to move damaged
  parts aside.
* ``_claims/<random>.claim``: one per running sweep, the keys it is computing and has
  not yet written (one a line, rewritten under the table lock). Its sweep holds a lock on
  it for as long as it runs: a claim whose lock can be taken belongs to a sweep that
  ended without removing it (killed), and is removed; its points are free again.
* ``_hardware``: held (``Share.hold``) by a campaign on real hardware for as long as it
  runs, so that a second one into the table is refused instead of driving the same rig.

Campaigns share a table the same way, claiming one point at a time
(``labbench.campaign.engine``): two campaigns of one spec on a simulator run every point
once between them (before, each ran every point).

A sweep claims the next few points of its spec that are neither in the table nor
claimed; once it has no more of its own it waits for the points others claimed, then
computes what they left (``labbench.sweep.engine``). So N sweeps of one spec compute
every point once and all end complete. (Before, two of four such sweeps computed every
point again and one ended in ``FileNotFoundError`` when another merged the parts.)

Locks are ``fcntl.flock`` (``msvcrt.locking`` on Windows): a lock dies with its process.
On a file system that does not honour them (some network shares) the sweeps still end
complete, but may compute a point twice.
"""
from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Iterator
from pathlib import Path

from labbench.errors import UserError
from labbench.safe_write import create_new, own_folder, why

try:
    import fcntl
except ImportError:  # Windows
    fcntl = None
try:
    import msvcrt
except ImportError:  # POSIX
    msvcrt = None

LOCK_FILE = "_lock"
CLAIMS = "_claims"
_OPEN = (os.O_RDWR | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
         | getattr(os, "O_BINARY", 0))


def _lock(fd: int, wait: bool) -> bool:
    """An exclusive lock on ``fd``'s file; False when another holds it and not ``wait``."""
    if fcntl is not None:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BlockingIOError:
            return False
        return True
    if msvcrt is not None:
        while True:
            try:
                os.lseek(fd, 0, os.SEEK_SET)
                msvcrt.locking(fd, msvcrt.LK_NBLCK, 1)
                return True
            except OSError:
                if not wait:
                    return False
                time.sleep(0.05)
    from labbench.platform import missing

    missing("file locks (fcntl, msvcrt)", "sweeps of one table at once may compute a point twice")
    return True


def _unlock(fd: int) -> None:
    if fcntl is not None:
        fcntl.flock(fd, fcntl.LOCK_UN)
    elif msvcrt is not None:
        os.lseek(fd, 0, os.SEEK_SET)
        with contextlib.suppress(OSError):
            msvcrt.locking(fd, msvcrt.LK_UNLCK, 1)


def _open_lock(path: Path) -> int:
    """The table's lock file, made if missing; a link at its name is not ours: it is removed
    (never followed) and the file made."""
    try:
        return os.open(path, _OPEN | os.O_CREAT, 0o666)
    except OSError:
        if not os.path.islink(path):
            raise
        os.unlink(path)
        return os.open(path, _OPEN | os.O_CREAT | os.O_EXCL, 0o666)


class Share:
    """This sweep's place in a table shared with others: the table lock (``locked``) and
    its claim (``claim``, ``release``, ``others``). ``close()`` removes the claim."""

    def __init__(self, directory):
        self.directory = Path(directory)
        self.mine: set[str] = set()
        self._held: list[int] = []  # descriptors of ``hold``'s locks
        try:
            self._lock_fd = _open_lock(self.directory / LOCK_FILE)
        except OSError as exc:
            raise UserError(f"cannot use sweep table {self.directory}: {why(exc)}") from None
        try:
            self.claims = own_folder(self.directory / CLAIMS)
            with self.locked():  # made and locked at once: never seen unlocked (as dead)
                self._fd, self.path = create_new(self.claims, "", ".claim")
                _lock(self._fd, wait=True)
        except OSError as exc:
            os.close(self._lock_fd)
            raise UserError(f"cannot use sweep table {self.directory}: {why(exc)}") from None
        except BaseException:
            os.close(self._lock_fd)
            raise

    @contextlib.contextmanager
    def locked(self) -> Iterator[None]:
        """The table's lock for the block (others wait for it)."""
        _lock(self._lock_fd, wait=True)
        try:
            yield
        finally:
            _unlock(self._lock_fd)

    def others(self) -> set[str]:
        """Keys the other running sweeps claimed (under ``locked``); a dead sweep's claim
        is removed on the way."""
        keys: set[str] = set()
        for p in self.claims.glob("*.claim"):
            if p == self.path:
                continue
            try:
                fd = os.open(p, _OPEN)
            except FileNotFoundError:
                continue
            except OSError:  # not ours to open (another user's sweep): read it as live
                with contextlib.suppress(OSError):
                    keys.update(p.read_text().split())
                continue
            try:
                if _lock(fd, wait=False):  # its sweep is gone
                    p.unlink(missing_ok=True)
                    continue
                keys.update(_read_all(fd).decode().split())
            finally:
                os.close(fd)
        return keys

    def claim(self, keys) -> None:
        """Add ``keys`` to this sweep's claim (under ``locked``)."""
        self.mine.update(keys)
        self._save()

    def release(self, keys) -> None:
        """Drop ``keys`` (written to the table, or given up) from the claim; takes the lock."""
        with self.locked():
            self.mine.difference_update(keys)
            self._save()

    def _save(self) -> None:
        os.ftruncate(self._fd, 0)
        data = "".join(f"{k}\n" for k in sorted(self.mine)).encode()
        os.lseek(self._fd, 0, os.SEEK_SET)
        while data:
            data = data[os.write(self._fd, data):]

    def hold(self, name: str) -> bool:
        """An exclusive lock on the table's file ``name`` for as long as this share is open;
        False when another process holds it."""
        try:
            fd = _open_lock(self.directory / name)
        except OSError as exc:
            raise UserError(f"cannot use table {self.directory}: {why(exc)}") from None
        if not _lock(fd, wait=False):
            os.close(fd)
            return False
        self._held.append(fd)
        return True

    def close(self) -> None:
        """Remove the claim and let go of the table (safe twice)."""
        if self._fd is None:
            return
        with contextlib.suppress(OSError):
            self.path.unlink()
        os.close(self._fd)  # its lock goes with it
        for fd in [self._lock_fd, *self._held]:
            os.close(fd)
        self._fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def wait_for_others(share: Share, stop, tick=None, poll_s: float = 0.5) -> bool:
    """Wait until no other user of the table has points claimed (they finish them, or their
    claims go with them); ``tick(n)`` hears how many they hold, every 2 s. False when
    ``stop`` is set meanwhile."""
    last = -float("inf")
    while stop is None or not stop.is_set():
        with share.locked():
            waiting = len(share.others())
        if not waiting:
            return True
        if tick is not None and time.monotonic() - last >= 2.0:
            last = time.monotonic()
            tick(waiting)
        time.sleep(poll_s)
    return False


def _read_all(fd: int) -> bytes:
    os.lseek(fd, 0, os.SEEK_SET)
    chunks = []
    while chunk := os.read(fd, 1 << 16):
        chunks.append(chunk)
    return b"".join(chunks)
