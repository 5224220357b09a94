"""The core depends on nothing that plugs into it.

The core is the physical ``labbench/`` folder less the CLI (``labbench/cli/``)
and the registry (``labbench/registry.py``), which find plug-ins by name. No
module of the core may import the drivers, simulators, protocols or the GUI,
nor Qt; every import statement is read, at any depth (lazy imports included).
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PLUGINS = ("labbench.drivers", "labbench.sim_backend", "labbench.protocols", "labbench.gui",
           "drivers", "sim_backend", "protocols", "gui", "PySide6", "pyqtgraph")


def _core_files():
    core = ROOT / "labbench"
    for path in sorted(core.rglob("*.py")):
        rel = path.relative_to(core)
        if rel.parts[0] == "cli" or rel == Path("registry.py"):
            continue
        yield path


def _imports(path: Path):
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.lineno, node.module
            for alias in node.names:  # from labbench import gui
                yield node.lineno, f"{node.module}.{alias.name}"


def _is_plugin(name: str) -> bool:
    return any(name == p or name.startswith(p + ".") for p in PLUGINS)


def test_core_imports_no_plugin():
    files = list(_core_files())
    assert len(files) > 20  # the walk found the core
    bad = [f"{p.relative_to(ROOT)}:{line}: {name}"
           for p in files for line, name in _imports(p) if _is_plugin(name)]
    assert bad == []


def test_the_check_sees_a_lazy_plugin_import(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("def f():\n    from labbench.protocols import chirp_id\n    import gui.app\n")
    assert [name for _, name in _imports(f) if _is_plugin(name)] == [
        "labbench.protocols", "labbench.protocols.chirp_id", "gui.app"]


def test_plugins_use_the_installed_namespace():
    """drivers/, protocols/, ... import each other as labbench.X, never by folder name."""
    bad = []
    for folder in ("drivers", "sim_backend", "protocols", "gui", "labbench", "tests", "bench"):
        for path in sorted((ROOT / folder).rglob("*.py")):
            for line, name in _imports(path):
                if name.split(".")[0] in ("drivers", "sim_backend", "protocols", "gui"):
                    bad.append(f"{path.relative_to(ROOT)}:{line}: {name}")
    assert bad == []


def test_every_package_folder_is_installed():
    """pyproject lists packages by hand (package-dir maps the folders): none may be missing.
    A folder of data only (sim_backend/avr: C source) is listed too, with its package-data,
    or setuptools warns that it would be ignored."""
    import tomllib

    tool = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]
    found = {".".join((top, *init.parent.relative_to(ROOT / folder).parts))
             for top, folder in tool["package-dir"].items()
             for init in (ROOT / folder).rglob("__init__.py")}
    data_only = set(tool["packages"]) - found
    assert found <= set(tool["packages"]) and data_only <= set(tool["package-data"])
