"""The byte pipe between a simulated serial board and the host's pyserial port.

POSIX: a pty pair (``os.openpty``); the host opens the slave by path, 8-bit clean
and fast, as it would a USB-serial board. Where there is no pty (Windows): a TCP
socket on 127.0.0.1 that the host opens as pyserial's ``socket://127.0.0.1:PORT``
URL. Either way the board writes without blocking (a full buffer loses bytes, as a
USB-serial bridge does when the host stops reading) and reads with a timeout.
"""
from __future__ import annotations

import errno
import importlib
import os
import select
import socket

from labbench.platform import missing

ACCEPT_TIMEOUT_S = 10.0  # the host connects right after opening: only a dead host waits this


def open_transport(warn=None):
    """A ``PtyTransport`` where the platform has ptys, else a ``SocketTransport`` (one line)."""
    if all(hasattr(os, n) for n in ("openpty", "ttyname")) and _importable("tty"):
        return PtyTransport()
    missing("a pseudo-terminal (os.openpty, termios)",
            "the simulated serial board talks over a local socket (pyserial socket://)", warn)
    return SocketTransport()


def _importable(name: str) -> bool:
    try:
        importlib.import_module(name)
    except ImportError:
        return False
    return True


class PtyTransport:
    """A pty pair; ``url`` is the slave's path."""

    def __init__(self):
        import tty

        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)  # no echo or line discipline before the host configures it
        os.set_blocking(self._master, False)
        self.url = os.ttyname(self._slave)

    def write(self, data: bytes) -> None:
        if self._master is None:
            return
        try:
            os.write(self._master, data)
        except BlockingIOError:
            pass

    def read(self, timeout: float) -> bytes:
        """Up to 4096 bytes from the host, waiting at most ``timeout``; b"" if none or closed."""
        if self._master is None:
            return b""
        r, _, _ = select.select([self._master], [], [], timeout)
        if not r:
            return b""
        try:
            return os.read(self._master, 4096)
        except OSError as exc:  # EIO: host side closed
            if exc.errno == errno.EIO:
                return b""
            raise

    def close(self) -> None:
        """Both ends gone: the host's port fails from now on (safe to call twice)."""
        for fd in (self._master, self._slave):
            if fd is not None:
                os.close(fd)
        self._master = self._slave = None


class SocketTransport:
    """A listening socket on 127.0.0.1; ``url`` is the host's ``socket://`` URL. The host's
    connection is accepted at the board's first read or write."""

    def __init__(self):
        self._listener = socket.create_server(("127.0.0.1", 0))
        self._conn: socket.socket | None = None
        self._closed = False
        self.url = f"socket://127.0.0.1:{self._listener.getsockname()[1]}"

    def _connection(self) -> socket.socket | None:
        if self._conn is None and not self._closed:
            self._listener.settimeout(ACCEPT_TIMEOUT_S)
            try:
                conn, _ = self._listener.accept()
            except OSError:  # timed out, or closed meanwhile
                return None
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # a frame is a packet
            conn.setblocking(False)
            self._conn = conn
        return self._conn

    def write(self, data: bytes) -> None:
        conn = self._connection()
        if conn is None:
            return
        try:
            conn.send(data)
        except (BlockingIOError, ConnectionError):
            pass

    def read(self, timeout: float) -> bytes:
        """Up to 4096 bytes from the host, waiting at most ``timeout``; b"" if none or closed."""
        conn = self._connection()
        if conn is None:
            return b""
        r, _, _ = select.select([conn], [], [], timeout)
        if not r:
            return b""
        try:
            return conn.recv(4096)
        except (BlockingIOError, ConnectionError):
            return b""

    def close(self) -> None:
        """The connection and the listener gone: the host's port fails from now on."""
        self._closed = True
        for s in (self._conn, self._listener):
            if s is not None:
                s.close()
        self._conn = None
