"""The layers of docs/DESIGN.md, read from the code's own imports (ast), so a new arrow that runs
back up fails here with the file, the line and the import that breaks the rule."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

#: What each layer of the project may import of the project (its own package included). A module
#: belongs to the longest prefix listed here.
ALLOWED: dict[str, tuple[str, ...]] = {
    "twin.core": (),
    "twin.lidar": ("twin.core",),
    "twin.stage": ("twin.core", "bench_fw"),
    "twin.sim": ("twin.core", "twin.lidar", "twin.stage", "models", "bench_fw"),
    "twin": ("twin.core",),  # the package's face
    "align": ("twin.core",),
    "models": (),
    "bench_fw": (),
    "scenarios": ("twin", "align", "models", "bench_fw"),
    "scenarios.line": ("scenarios", "twin", "align", "models", "bench_fw"),
    "aimbench": ("scenarios.envs",),
}
PROJECT = ("twin", "align", "scenarios", "models", "bench_fw", "aimbench")

#: Third-party libraries that only one place of the project may import.
CONFINED: dict[str, tuple[str, ...]] = {
    "rerun": ("scenarios.recording",),
    "gymnasium": ("scenarios.envs",),
    "mujoco": ("twin.sim", "scenarios"),
    # the line station's web framework and OPC UA server live in its own folder
    "nicegui": ("scenarios.line",),
    "asyncua": ("scenarios.line",),
}


def _module_of(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _layer(module: str, layers: dict[str, tuple[str, ...]]) -> str | None:
    best = None
    for name in layers:
        if (module == name or module.startswith(name + ".")) and (
                best is None or len(name) > len(best)):
            best = name
    return best


def _within(module: str, prefixes: tuple[str, ...]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import in the file, at any depth (lazy imports count too)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = _module_of(path) if path.name == "__init__.py" else _module_of(path).rpartition(
        ".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                mod = ".".join([*base, node.module] if node.module else base)
            else:
                mod = node.module or ""
            # `from twin.core import vlp16` imports the module twin.core.vlp16, `from twin.core.scan
            # import Scan` the module twin.core.scan.
            for a in node.names:
                sub = f"{mod}.{a.name}"
                found.append((node.lineno, sub if _is_module(sub) else mod))
    return found


def _is_module(name: str) -> bool:
    path = REPO.joinpath(*name.split("."))
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def _project_files() -> list[Path]:
    files = []
    for top in PROJECT:
        files += sorted((REPO / top).rglob("*.py"))
    return [f for f in files if "build" not in f.relative_to(REPO).parts]


def test_every_layer_imports_only_what_it_may():
    broken = []
    for path in _project_files():
        module = _module_of(path)
        layer = _layer(module, ALLOWED)
        assert layer is not None, f"{path}: in no layer of ALLOWED; add its folder there"
        allowed = (layer, *ALLOWED[layer])
        for line, imported in _imports(path):
            if _within(imported, PROJECT) and not _within(imported, allowed):
                broken.append(f"{path.relative_to(REPO)}:{line} imports {imported}: {layer} may "
                              f"import only {', '.join(allowed)}")
    assert not broken, "\n".join(broken)


@pytest.mark.parametrize("library", sorted(CONFINED))
def test_confined_libraries_are_imported_in_one_place(library):
    broken = []
    for path in _project_files():
        module = _module_of(path)
        for line, imported in _imports(path):
            if _within(imported, (library,)) and not _within(module, CONFINED[library]):
                broken.append(f"{path.relative_to(REPO)}:{line} imports {imported}: only "
                              f"{', '.join(CONFINED[library])} may")
    assert not broken, "\n".join(broken)


@pytest.mark.parametrize("module", ["align", "twin.core.scan", "twin.lidar.capture",
                                    "twin.stage.controller"])
def test_importing_the_lower_layers_loads_no_simulator(module):
    code = (f"import sys, {module}; bad = [m for m in ('mujoco', 'rerun', 'gymnasium', "
            "'scenarios', 'twin.sim') if m in sys.modules]; assert not bad, bad")
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True,
                         timeout=120)
    assert res.returncode == 0, res.stderr.strip().splitlines()[-1]


def test_the_layer_rule_catches_an_arrow_back_up(tmp_path):
    """The checker itself: an import from the data path into the simulator is reported."""
    bad = REPO / "twin" / "lidar" / "_layer_probe.py"
    bad.write_text("from twin.sim.bench import BenchSim\n", encoding="utf-8")
    try:
        with pytest.raises(AssertionError, match=r"_layer_probe.py:1 imports twin.sim.bench"):
            test_every_layer_imports_only_what_it_may()
    finally:
        bad.unlink()


def test_the_firmware_main_defines_only_setup_and_loop():
    """Other units call into system.cpp, never into main.cpp: no call circle through main."""
    src = (REPO / "bench_fw" / "src" / "main.cpp").read_text(encoding="utf-8")
    defined = re.findall(r"^(?!static\b)[A-Za-z_][\w:<>\s\*&]*?\b(\w+)\s*\([^;{]*\)\s*\{", src,
                         re.MULTILINE)
    assert sorted(defined) == ["loop", "setup"], defined
