"""Every file labbench writes (exports, reports, figures) goes through here.

Rules, checked before any work and again at the moment of writing:

* never onto one of the command's inputs (``export SESSION --csv SESSION``), not
  even with ``force``;
* an existing output is replaced only with ``force`` (the CLI's ``--force``);
  the GUI picks a free name instead (``free_name``);
* the folder holding the output must exist: no folder is created that the
  user did not name (``output_folder`` creates exactly the one named, never
  its parents);
* the data go to a temporary file in the same folder that is renamed into
  place when complete, so an interrupted write leaves the old file (or no
  file), never a truncated one. A symlink at the output name is replaced as
  a link, never followed, so nothing outside the folder is written.
"""
from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from labbench.errors import UserError


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


def output_folder(path) -> Path:
    """The named output folder, created if missing (its parent must exist)."""
    if not str(path).strip():
        raise UserError("empty output folder name")
    d = Path(path)
    if d.exists() and not d.is_dir():
        raise UserError(f"output {d} is a file, not a folder")
    try:
        d.mkdir(exist_ok=True)
    except FileNotFoundError:
        raise UserError(f"cannot create output folder {d}: {d.parent} does not exist "
                        "(labbench creates no folders you did not name)") from None
    except OSError as exc:
        raise UserError(f"cannot create output folder {d}: {exc.strerror}") from None
    return d


def free_name(path) -> Path:
    """``path``, or ``<stem>-2<suffix>``, ``-3`` ... : the first name not taken."""
    p = Path(path)
    n = 1
    while os.path.lexists(p):
        n += 1
        p = p.with_name(f"{Path(path).stem}-{n}{Path(path).suffix}")
    return p


@contextlib.contextmanager
def replacing(path, inputs: Iterable = (), force: bool = False) -> Iterator[Path]:
    """Write ``path`` atomically: yields a temporary path (same folder, same suffix, so
    writers that go by the suffix pick the right format) that becomes ``path`` when the
    block ends without an exception; otherwise it is removed."""
    inputs = list(inputs)
    out = output_path(path, inputs, force)
    try:
        fd, name = tempfile.mkstemp(dir=out.parent, prefix=f".{out.name}.",
                                    suffix=f".part{out.suffix}")
    except OSError as exc:
        raise UserError(f"cannot write into {out.parent}: {exc.strerror}") from None
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        _fsync(tmp)
        output_path(out, inputs, force)  # again: the folder may have changed meanwhile
        _publish(tmp, out, force)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def _fsync(path: Path) -> None:
    # Writable: Windows' fsync (_commit) refuses a read-only descriptor.
    fd = os.open(path, os.O_RDWR | getattr(os, "O_BINARY", 0))
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
        return
    tmp.unlink()
