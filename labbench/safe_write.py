"""Every file labbench writes goes through here: exports, reports, figures, sweep tables and
charts, sessions (``labbench.sessions.session_format``) and rig edits (``edit_text``).

Rules, checked before any work and again at the moment of writing:

* never onto one of the command's inputs (``export SESSION --csv SESSION``), not
  even with ``force``;
* an existing output is replaced only with ``force`` (the CLI's ``--force``);
  the GUI picks a free name instead (``free_name``);
* the folder holding the output must exist: no folder is created that the
  user did not name (``output_folder`` creates exactly the one named, never
  its parents, and refuses a link at its name; ``new_folder`` also removes it again when
  what was to go into it failed);
* the data go to a new file in the same folder that is renamed into place when
  complete, so an interrupted write leaves the old file (or no file), never a
  truncated one;
* a file the tool creates is created exclusively (``O_CREAT | O_EXCL | O_NOFOLLOW``)
  under a random name (``create_new``): a link planted at any name is never
  followed. A symlink at the output name is replaced as a link, so nothing
  outside the folder is written;
* a new file has the user's umask (0666 less the umask, as any program's files:
  ``tempfile.mkstemp``'s 0600 kept a supervisor logged in as another user from
  reading a report); a replaced one keeps its mode;
* what cannot be done safely is refused in one line (``UserError``): a read-only
  file or folder to edit, a folder that refuses a new file, a write the disk refused.
"""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
import stat
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from labbench.errors import UserError

# O_NOFOLLOW: the last component is never a link; O_BINARY (Windows): no newline translation
_CREATE = (os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0)
           | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0))
# what a person is told a refused write means (errno -> words)
_WHY = {errno.ENOSPC: "the disk is full",
        getattr(errno, "EDQUOT", -1): "the disk quota is used up",
        errno.EFBIG: "the file size limit was reached", errno.EROFS: "the file system is read-only",
        errno.EACCES: "permission denied", errno.EPERM: "operation not permitted",
        errno.EIO: "a disk input/output error"}


def why(exc: OSError) -> str:
    """A refused write in words: ``the disk is full (No space left on device)``."""
    text = exc.strerror or str(exc)
    words = _WHY.get(exc.errno)
    return f"{words} ({text})" if words and words.lower() != text.lower() else text


def _same_file(a: os.stat_result, path) -> bool:
    try:
        b = os.stat(path)
    except (OSError, ValueError):
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def output_path(path, inputs: Iterable = (), force: bool = False) -> Path:
    """``path`` as a ``Path`` once it is a fit place for a new file; else a UserError."""
    p = Path(path)
    if not str(path).strip():
        raise UserError("empty output file name")
    if p.is_dir():
        raise UserError(f"output {p} is a directory; give a file name")
    parent = p.parent
    if not parent.is_dir():
        raise UserError(f"output folder {parent} does not exist (labbench creates no folders "
                        "you did not name)")
    try:
        st = os.stat(p)  # follows a link: is the data behind it one of the inputs?
    except FileNotFoundError:
        st = None
    except OSError as exc:
        raise UserError(f"cannot use output {p}: {exc.strerror}") from None
    if st is not None and any(_same_file(st, i) for i in inputs):
        raise UserError(f"output {p} is an input of this command; choose another name")
    if os.path.lexists(p):
        if st is not None and not stat.S_ISREG(st.st_mode):
            raise UserError(f"output {p} exists and is not a regular file")
        if not force:
            raise UserError(f"output {p} exists; give --force to replace it")
    return p


def usable_folder(path) -> Path:
    """``path`` once it can be an output folder (``output_folder``), without making it: no
    link at its name (never followed: labbench writes its tables, charts and reports into
    real folders only; a link planted at ``NAME.charts`` had a campaign's report written
    wherever it pointed), not a file."""
    if not str(path).strip():
        raise UserError("empty output folder name")
    d = Path(path)
    if os.path.islink(d):
        raise UserError(f"output folder {d} is a link: labbench writes only into a real "
                        "folder (give the folder it points at, or remove the link)")
    if d.exists() and not d.is_dir():
        raise UserError(f"output {d} is a file, not a folder")
    return d


def output_folder(path) -> Path:
    """The named output folder (``usable_folder``), created if missing (its parent must
    exist)."""
    d = usable_folder(path)
    try:
        d.mkdir(exist_ok=True)
    except FileNotFoundError:
        raise UserError(f"cannot create output folder {d}: {d.parent} does not exist "
                        "(labbench creates no folders you did not name)") from None
    except OSError as exc:
        raise UserError(f"cannot create output folder {d}: {why(exc)}") from None
    return d


@contextlib.contextmanager
def new_folder(path) -> Iterator[Path]:
    """``output_folder(path)`` for the block; a folder this made is removed again when the
    block fails and left it empty (a report on a full disk left an empty folder behind)."""
    made = not os.path.lexists(path)
    d = output_folder(path)
    try:
        yield d
    except BaseException:
        if made:
            with contextlib.suppress(OSError):
                d.rmdir()  # only when empty
        raise


def writable_folder(path, what: str = "folder") -> Path:
    """``path`` once a new file can be made in it (one is made and removed); else one
    UserError saying why (no permission, read-only, no space for its entry)."""
    d = Path(path)
    try:
        fd, probe = create_new(d, ".labbench-probe-", "")
    except FileNotFoundError:
        raise UserError(f"{what} {d} does not exist") from None
    except OSError as exc:
        raise UserError(f"cannot write into {what} {d}: {why(exc)}") from None
    os.close(fd)
    with contextlib.suppress(OSError):
        probe.unlink()
    return d


def own_folder(path) -> Path:
    """A folder the tool keeps inside its own (a sweep table's claims, its damaged parts):
    made if missing; a link or a file at its name is refused, never followed."""
    p = Path(path)
    try:
        os.mkdir(p)
    except FileExistsError:
        pass
    except OSError as exc:
        raise UserError(f"cannot create folder {p}: {why(exc)}") from None
    if not stat.S_ISDIR(os.lstat(p).st_mode):
        raise UserError(f"{p} is not a folder (a link or a file where labbench keeps its own "
                        "folder): remove it")
    return p


def free_name(path) -> Path:
    """``path``, or ``<stem>-2<suffix>``, ``-3`` ... : the first name not taken."""
    p = Path(path)
    n = 1
    while os.path.lexists(p):
        n += 1
        p = p.with_name(f"{Path(path).stem}-{n}{Path(path).suffix}")
    return p


def _token() -> str:
    return secrets.token_hex(6)


def create_new(folder, prefix: str, suffix: str, mode: int | None = None) -> tuple[int, Path]:
    """A new empty file ``<prefix><random><suffix>`` in ``folder``, created exclusively and
    never through a link (a name taken, by a file or a planted link, is passed over):
    ``(descriptor, path)``. Its mode: the umask's (``tempfile.mkstemp`` would give 0600),
    or ``mode``."""
    for _ in range(100):
        p = Path(folder) / f"{prefix}{_token()}{suffix}"
        try:
            fd = os.open(p, _CREATE, 0o666)
        except FileExistsError:
            continue
        if mode is not None:
            try:
                (os.fchmod(fd, mode) if hasattr(os, "fchmod") else os.chmod(p, mode))
            except BaseException:
                os.close(fd)
                p.unlink()
                raise
        return fd, p
    raise FileExistsError(errno.EEXIST, "no free name", str(folder))


def _mode_of(path: Path) -> int | None:
    """The permission bits of the regular file at ``path`` (not through a link), else None."""
    try:
        st = os.lstat(path)
    except OSError:
        return None
    return stat.S_IMODE(st.st_mode) & 0o777 if stat.S_ISREG(st.st_mode) else None


@contextlib.contextmanager
def replacing(path, inputs: Iterable = (), force: bool = False) -> Iterator[Path]:
    """Write ``path`` atomically: yields a new file's path (same folder, same suffix, so
    writers that go by the suffix pick the right format) that becomes ``path`` when the
    block ends without an exception; otherwise it is removed. A write the system refuses
    (full disk, size limit, permission) is one UserError."""
    inputs = list(inputs)
    out = output_path(path, inputs, force)

    def publish(tmp: Path) -> None:
        output_path(out, inputs, force)  # again: the folder may have changed meanwhile
        _publish(tmp, out, force)

    with _staged(out.parent, f".{out.name}.", f".part{out.suffix}", _mode_of(out), out,
                 publish) as tmp:
        yield tmp


@contextlib.contextmanager
def new_output(folder, prefix: str, suffix: str) -> Iterator[Path]:
    """Like ``replacing`` for a file whose name only has to be new (``<prefix><random>
    <suffix>``, e.g. a sweep's part files): never replaces anything. Yields the new file's
    path; the block's result is published under the final name when it ends."""
    d = Path(folder)

    def publish(tmp: Path) -> None:
        for _ in range(100):
            name = d / f"{prefix}{_token()}{suffix}"
            try:
                os.link(tmp, name)  # fails on any name taken, a planted link included
                return
            except FileExistsError:
                continue
            except OSError as exc:
                if exc.errno not in (errno.EPERM, errno.ENOTSUP, errno.EXDEV):
                    raise
                if not os.path.lexists(name):  # a file system without hard links
                    os.replace(tmp, name)
                    return
        raise FileExistsError(errno.EEXIST, "no free name", str(d))

    with _staged(d, f".{prefix}", f".part{suffix}", None, d, publish) as tmp:
        yield tmp


@contextlib.contextmanager
def _staged(folder: Path, prefix: str, suffix: str, mode: int | None, what: Path,
            publish: Callable[[Path], None]) -> Iterator[Path]:
    """A new file in ``folder`` for the block to fill, flushed and ``publish``ed when the
    block ends, removed in any case (``publish`` links or renames it); a refused write is
    one UserError naming ``what``."""
    try:
        fd, tmp = create_new(folder, prefix, suffix, mode)
    except OSError as exc:
        raise UserError(f"cannot write into {folder}: {why(exc)}") from None
    os.close(fd)
    try:
        try:
            yield tmp
            _fsync(tmp)
            publish(tmp)
        except OSError as exc:
            raise UserError(f"cannot write {what}: {why(exc)}") from None
    finally:
        with contextlib.suppress(OSError):
            tmp.unlink()


def _fsync(path: Path) -> None:
    # Writable: Windows' fsync (_commit) refuses a read-only descriptor.
    fd = os.open(path, os.O_RDWR | getattr(os, "O_BINARY", 0) | getattr(os, "O_NOFOLLOW", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _publish(tmp: Path, out: Path, force: bool) -> None:
    if force:
        os.replace(tmp, out)  # a symlink at ``out`` is replaced, not followed
        return
    try:
        os.link(tmp, out)  # fails if ``out`` appeared meanwhile: no silent clobber
    except FileExistsError:
        raise UserError(f"output {out} exists; give --force to replace it") from None
    except OSError:  # a file system without hard links: the check above stands
        os.replace(tmp, out)


def write_file(path, data: bytes, mode: int | None = None) -> Path:
    """``data`` as the whole of ``path``: a new file written, flushed and renamed onto it (a
    link at ``path`` is replaced, never followed). Mode: ``mode``, else the old file's, else
    the umask's. OSError when the system refuses."""
    out = Path(path)
    mode = _mode_of(out) if mode is None else mode
    fd, tmp = create_new(out.parent, f".{out.name}.", ".tmp", mode)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, out)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise
    return out


@dataclass(frozen=True)
class Edit:
    """What ``edit_text`` did: the file named, the file written (its real path when the name
    is a link), the backup of its old content (None when nothing changed)."""

    path: Path
    real: Path
    backup: Path | None

    @property
    def through_link(self) -> bool:
        return self.real != Path(os.path.abspath(self.path))


def editable(path, what: str = "file") -> Path:
    """The real path of ``path`` (a link followed, as an editor writes through one) once it
    can be edited safely: a regular file its owner may write, in a folder that takes a new
    file. Else one UserError saying why."""
    p = Path(path)
    try:
        real = Path(os.path.realpath(p, strict=True))
        st = os.stat(real)
    except FileNotFoundError:
        raise UserError(f"{what} {p} does not exist" + (" (a link to a missing file)"
                                                         if p.is_symlink() else "")) from None
    except OSError as exc:
        raise UserError(f"cannot use {what} {p}: {why(exc)}") from None
    if not stat.S_ISREG(st.st_mode):
        raise UserError(f"{what} {p} is not a regular file")
    writable_folder(real.parent, f"the folder of {what} {p},")  # the new file and the backup
    if not st.st_mode & stat.S_IWUSR or not os.access(real, os.W_OK):
        raise UserError(f"{what} {p} is read-only: make it writable to let labbench change it")
    return real


def edit_text(path, change: Callable[[str], str | None], what: str = "file",
              backup_suffix: str = ".bak") -> Edit:
    """Change a UTF-8 text file in place, safely (``editable``): ``change(text)`` gets the
    text with LF line breaks and returns the new text (None: no change). The file keeps its
    mode and its line breaks (CRLF stays CRLF); its old content goes first to
    ``<real name><backup_suffix>`` beside it, written the same way (a link there is
    replaced, not followed). One UserError when reading or writing is refused."""
    real = editable(path, what)
    try:
        raw = real.read_bytes()
    except OSError as exc:
        raise UserError(f"cannot read {what} {path}: {why(exc)}") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise UserError(f"{what} {path} is not UTF-8 text (byte {exc.start})") from None
    crlf = raw.count(b"\r\n") * 2 > raw.count(b"\n")
    new = change(text.replace("\r\n", "\n") if crlf else text)
    if new is None:
        return Edit(Path(path), real, None)
    data = (new.replace("\n", "\r\n") if crlf else new).encode("utf-8")
    mode = _mode_of(real)
    backup = real.with_name(real.name + backup_suffix)
    try:
        write_file(backup, raw, mode)
        write_file(real, data, mode)
    except OSError as exc:
        raise UserError(f"cannot write {what} {path}: {why(exc)}; it is unchanged") from None
    return Edit(Path(path), real, backup)
