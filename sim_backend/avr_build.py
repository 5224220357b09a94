"""Build the reference sketch for an ATmega328P and the simavr harness that runs it.

The sketch (docs/arduino/labbench_encoder.ino) is compiled with Debian's
``gcc-avr``/``avr-libc`` against the Arduino core of ``arduino-core-avr``, using
that core's own ``platform.txt`` recipes and the ``uno`` entry of its
``boards.txt`` (what the Arduino IDE runs, without the IDE). The harness
(``sim_backend/avr/harness.c``) is linked against ``libsimavr.so.2`` alone; the
simavr headers come from the ``libsimavr-dev`` package, unpacked into the cache
with ``apt-get download`` + ``dpkg-deb -x`` when they are not installed (the
package itself would pull Mesa in through ``libsimavrparts``).

Outputs go to a cache folder (``$LABBENCH_AVR_CACHE`` or
``~/.cache/labbench/avr``), one subfolder per hash of everything that goes into
them, so tests rebuild only when a source or a flag changes. Packages: ``make
avr-deps`` installs them (see the Makefile).
"""

from __future__ import annotations

import hashlib
import os
import re
import shlex
import shutil
import subprocess
import tempfile
from pathlib import Path

from labbench.errors import MissingExtraError

CORE_ROOT = Path("/usr/share/arduino/hardware/arduino/avr")
BOARD = "uno"
# arduino-core-avr 1.8.7 with gcc-avr 5.4: WString.cpp uses DECIMAL_DIG, which
# this avr-libc's <float.h> does not define; the compiler's own macro is the value.
CORE_FIX_FLAGS = "-DDECIMAL_DIG=__DECIMAL_DIG__"
IDE_VERSION = "10807"
SIMAVR_LIB = "libsimavr.so.2"
HERE = Path(__file__).resolve().parent
HARNESS_SRC = HERE / "avr" / "harness.c"
SKETCH = HERE.parent / "docs" / "arduino" / "labbench_encoder.ino"
APT_PACKAGES = ("gcc-avr", "avr-libc", "binutils-avr", "arduino-core-avr", "libsimavr2")


class AvrToolchainMissing(MissingExtraError):
    """What the firmware build needs is not installed (one line: what to install)."""


def cache_root() -> Path:
    env = os.environ.get("LABBENCH_AVR_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "labbench" / "avr"


def missing_tools() -> list[str]:
    """Names of what is missing for a build (empty when everything is there)."""
    missing = [t for t in ("avr-gcc", "avr-g++", "avr-gcc-ar", "cc") if shutil.which(t) is None]
    if not (CORE_ROOT / "platform.txt").is_file():
        missing.append("arduino-core-avr")
    if _simavr_library() is None:
        missing.append("libsimavr2")
    return missing


def problem() -> str | None:
    """Why the firmware cannot be built and run here (one line), or None."""
    missing = missing_tools()
    if missing:
        return f"{', '.join(missing)} missing: make avr-deps"
    try:
        simavr_include_dir()
    except AvrToolchainMissing as exc:
        return str(exc)
    return None


def _require_tools() -> None:
    missing = missing_tools()
    if missing:
        raise AvrToolchainMissing(
            f"the AVR firmware build needs {', '.join(missing)}: run `make avr-deps` "
            f"(apt-get install {' '.join(APT_PACKAGES)})"
        )


def _simavr_library() -> Path | None:
    for d in ("/usr/lib/x86_64-linux-gnu", "/usr/lib/aarch64-linux-gnu", "/usr/lib", "/usr/local/lib"):
        p = Path(d) / SIMAVR_LIB
        if p.exists():
            return p
    return None


# -- Arduino property files ---------------------------------------------------------------
def read_properties(path: Path) -> dict[str, str]:
    props = {}
    for line in path.read_text().splitlines():
        line = line.strip()
        if line and not line.startswith("#") and "=" in line:
            key, value = line.split("=", 1)
            props[key.strip()] = value.strip()
    return props


def expand(template: str, props: dict[str, str]) -> str:
    """Substitute ``{name}`` from ``props`` until nothing known is left (Arduino's rule:
    unknown names stay as they are)."""
    pattern = re.compile(r"\{([^{}]+)\}")
    for _ in range(20):
        new = pattern.sub(lambda m: props.get(m[1], m[0]), template)
        if new == template:
            return new
        template = new
    raise ValueError(f"recursive property in {template!r}")


def _build_properties(build_path: Path, defines: dict[str, object]) -> dict[str, str]:
    props = read_properties(CORE_ROOT / "platform.txt")
    prefix = BOARD + "."
    for key, value in read_properties(CORE_ROOT / "boards.txt").items():
        if key.startswith(prefix):
            props[key[len(prefix) :]] = value
    props.update(
        {
            "runtime.ide.version": IDE_VERSION,
            "runtime.platform.path": str(CORE_ROOT),
            "build.arch": "AVR",
            "build.path": str(build_path),
            "build.project_name": "sketch",
            "build.core.path": str(CORE_ROOT / "cores" / props["build.core"]),
            "build.variant.path": str(CORE_ROOT / "variants" / props["build.variant"]),
            "archive_file": "core.a",
            "archive_file_path": str(build_path / "core.a"),
            "compiler.path": "",  # avr-gcc from PATH (Debian puts it in /usr/bin)
        }
    )
    extra = " ".join([CORE_FIX_FLAGS] + [f"-D{k}={v}" for k, v in sorted(defines.items())])
    for lang in ("c", "cpp", "S"):
        props[f"compiler.{lang}.extra_flags"] = extra
    props["includes"] = (
        f'"-I{props["build.core.path"]}" "-I{props["build.variant.path"]}"'
    )
    return props


def _run_recipe(props: dict[str, str], name: str, **values: str) -> None:
    cmd = shlex.split(expand(props[name], {**props, **values}))
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode:
        raise RuntimeError(f"{name} failed ({' '.join(cmd)}):\n{proc.stderr[-4000:]}")


def _digest(*parts: object) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(p.read_bytes() if isinstance(p, Path) else repr(p).encode())
    return h.hexdigest()[:16]


def _tool_version(tool: str) -> str:
    return subprocess.run([tool, "--version"], capture_output=True, text=True).stdout.split("\n")[0]


def build_firmware(defines: dict[str, object] | None = None, sketch: Path = SKETCH) -> Path:
    """Compile ``sketch`` for the Uno (ATmega328P, 16 MHz); returns the Intel HEX path
    (``sketch.elf`` beside it).

    ``defines`` become ``-DNAME=value`` (the sketch's ``#ifndef`` settings). The
    core is compiled once per toolchain and archived (``core.a``), as the IDE does.
    """
    _require_tools()
    defines = dict(defines or {})
    if not sketch.is_file():
        raise AvrToolchainMissing(
            f"the reference sketch {sketch} is not here: the avr-sim device needs a "
            "source checkout of labbench (docs/arduino/)"
        )
    core_dir = CORE_ROOT / "cores" / "arduino"
    core_sources = sorted(p for p in core_dir.iterdir() if p.suffix in (".c", ".cpp", ".S"))
    key = _digest(sketch, defines, _tool_version("avr-gcc"), CORE_ROOT / "platform.txt",
                  *core_sources)
    out = cache_root() / f"fw-{key}"
    hex_file = out / "sketch.hex"
    if hex_file.is_file():
        return hex_file
    tmp = Path(tempfile.mkdtemp(prefix="fw-", dir=_ensure(cache_root())))
    props = _build_properties(tmp, defines)
    objects = []
    for src in core_sources:
        recipe = {".c": "recipe.c.o.pattern", ".cpp": "recipe.cpp.o.pattern", ".S": "recipe.S.o.pattern"}
        obj = tmp / (src.name + ".o")
        _run_recipe(props, recipe[src.suffix], source_file=str(src), object_file=str(obj))
        _run_recipe(props, "recipe.ar.pattern", object_file=str(obj))
    # The IDE's sketch preprocessing adds `#include <Arduino.h>` and prototypes; the
    # sketch includes Arduino.h itself and defines every function before its use.
    cpp = tmp / "sketch.ino.cpp"
    cpp.write_text(f'#line 1 "{sketch}"\n' + sketch.read_text())
    sketch_obj = tmp / "sketch.ino.cpp.o"
    _run_recipe(props, "recipe.cpp.o.pattern", source_file=str(cpp), object_file=str(sketch_obj))
    objects.append(f'"{sketch_obj}"')
    _run_recipe(props, "recipe.c.combine.pattern", object_files=" ".join(objects))
    _run_recipe(props, "recipe.objcopy.hex.pattern")
    _publish(tmp, out)
    return hex_file


def simavr_include_dir() -> Path:
    """simavr's headers: installed ones, else unpacked from the libsimavr-dev .deb."""
    installed = Path("/usr/include/simavr")
    if (installed / "sim_avr.h").is_file():
        return installed
    unpacked = cache_root() / "simavr-dev" / "usr" / "include" / "simavr"
    if (unpacked / "sim_avr.h").is_file():
        return unpacked
    work = Path(tempfile.mkdtemp(prefix="simavr-dev-", dir=_ensure(cache_root())))
    try:
        proc = subprocess.run(
            ["apt-get", "download", "libsimavr-dev"], cwd=work, capture_output=True, text=True
        )
        debs = list(work.glob("libsimavr-dev_*.deb"))
        if proc.returncode or not debs:
            raise AvrToolchainMissing(
                "simavr headers missing and `apt-get download libsimavr-dev` failed "
                f"({proc.stderr.strip().splitlines()[-1:] or proc.returncode}): run `make avr-deps`"
            )
        subprocess.run(["dpkg-deb", "-x", str(debs[0]), str(work / "x")], check=True)
        _publish(work / "x", cache_root() / "simavr-dev")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return unpacked


def build_harness() -> Path:
    """Compile the harness (C) against libsimavr.so.2; returns the executable's path."""
    _require_tools()
    include = simavr_include_dir()
    lib = _simavr_library()
    key = _digest(HARNESS_SRC, include / "sim_avr.h", str(lib), _tool_version("cc"))
    out = cache_root() / f"harness-{key}"
    exe = out / "avr_harness"
    if exe.is_file():
        return exe
    tmp = Path(tempfile.mkdtemp(prefix="harness-", dir=_ensure(cache_root())))
    cmd = ["cc", "-O2", "-std=gnu11", "-Wall", "-Wextra", f"-I{include}",
           str(HARNESS_SRC), "-o", str(tmp / "avr_harness"), str(lib), "-lm", "-lutil"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode:
        raise RuntimeError(f"harness build failed ({' '.join(cmd)}):\n{proc.stderr[-4000:]}")
    _publish(tmp, out)
    return exe


def _ensure(d: Path) -> Path:
    d.mkdir(parents=True, exist_ok=True)
    return d


def _publish(tmp: Path, out: Path) -> None:
    """Move a finished build into place (a concurrent build of the same key may win)."""
    try:
        tmp.rename(out)
    except OSError:
        shutil.rmtree(tmp, ignore_errors=True)
        if not out.exists():
            raise
