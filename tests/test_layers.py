"""The layers of docs/DESIGN.md, read from the code's own imports (ast), so a new arrow that runs
back up fails here with the file, the line and the import that breaks the rule."""

from __future__ import annotations

import ast
import functools
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

#: Within align: what each part may import of align besides itself (docs/DESIGN.md, "align's
#: stages"). The stages import one way, plane <- search <- fit <- posterior <- rays <- api: the
#: board search fits planes, the pose fit starts from a search's candidate, the posterior reads
#: the fit's model, the rays pipeline runs them all, api dispatches. The baselines (the paper's
#: method, ICP) use the search and the plane only; the design bound is geometry alone. COMMON are
#: the shared modules every stage may use; they import no stage. The leaf of float helpers
#: (floats) imports only the decorator that compiles it (jit), and jit nothing of align.
ALIGN_COMMON = ("align.board", "align.geometry", "align.result", "align.symmetry",
                "align.params", "align.methods", "align.hint_defaults", "align.floats",
                "align.jit")
_PLANE = (*ALIGN_COMMON,)
_SEARCH = (*_PLANE, "align.plane")
_FIT = (*_SEARCH, "align.search")
_POSTERIOR = (*_FIT, "align.fit")
_RAYS = (*_POSTERIOR, "align.posterior")
ALIGN_ALLOWED: dict[str, tuple[str, ...]] = {
    "align.jit": (),
    "align.floats": ("align.jit",),
    "align.board": (),
    "align.geometry": (),
    # the hints' defaults the command line shows, as plain numbers (align.hint_defaults)
    "align.result": ("align.hint_defaults",),
    "align.hint_defaults": (),
    "align.params": (),
    "align.methods": (),
    "align.symmetry": ("align.board", "align.geometry"),
    "align.calibration": ("align.board", "align.geometry"),
    "align.plane": _PLANE,
    "align.search": _SEARCH,
    "align.fit": _FIT,
    "align.posterior": _POSTERIOR,
    "align.rays": _RAYS,
    "align.baselines": (*ALIGN_COMMON, "align.plane", "align.search"),
    "align.design": ("align.board", "align.geometry"),
    # the board's choice between candidates: their estimates and the hints, nothing else
    "align.choice": ("align.geometry", "align.result"),
    "align.api": (*_RAYS, "align.rays", "align.baselines", "align.choice"),
    # the package's face
    "align": ("align.api", "align.board", "align.result", "align.methods"),
}
#: Inside scenarios/ the command line is the top: only the commands and the CLI that finds them
#: import a command; what a lower module needs of one moves down (e.g. `scenarios.versions`).
COMMANDS = "scenarios.commands"
COMMAND_IMPORTERS = ("scenarios.commands", "scenarios.cli")
#: Code outside the layers that the private-name rule reads too.
TOOLS = ("benchmarks", "tools")

#: Third-party libraries that only one place of the project may import.
CONFINED: dict[str, tuple[str, ...]] = {
    "rerun": ("scenarios.recording",),
    "gymnasium": ("scenarios.envs",),
    "mujoco": ("twin.sim", "scenarios"),
    # the line station's web framework and OPC UA server live in its own folder
    "nicegui": ("scenarios.line",),
    "asyncua": ("scenarios.line",),
    # ouster-sdk through one adapter (OSF in and out, its decode for the tests), loaded lazily:
    # the decoders and every parser stay free of it
    "ouster": ("twin.lidar.ouster_sdk",),
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


@functools.cache
def _tree(path: Path) -> ast.Module:
    """The file's syntax tree, parsed once for all the rules here (the probes are new files)."""
    return ast.parse(path.read_text(encoding="utf-8"), filename=str(path))


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every import in the file, at any depth (lazy imports count too)."""
    tree = _tree(path)
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


@functools.cache
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


def _align_broken(module: str, imports: list[tuple[int, str]]) -> list[str]:
    """The imports of align module ``module`` that break `ALIGN_ALLOWED`, as (line: why)."""
    part = _layer(module, ALIGN_ALLOWED)
    assert part is not None, f"{module}: in no part of ALIGN_ALLOWED; add it there"
    allowed = (part, *ALIGN_ALLOWED[part])
    return [f"{line} imports {imported}: {part} may import only "
            f"{', '.join(allowed) if allowed else 'nothing'} of align"
            for line, imported in imports
            if _within(imported, ("align",)) and imported != "align"
            and not _within(imported, allowed)]


def test_align_stages_import_one_way():
    broken = []
    for path in sorted((REPO / "align").rglob("*.py")):
        broken += [f"{path.relative_to(REPO)}:{why}"
                   for why in _align_broken(_module_of(path), _imports(path))]
    assert not broken, "\n".join(broken)


def test_the_align_rule_catches_a_stage_importing_upward():
    """The checker itself, on made-up imports: the search importing the fit, the leaf importing
    the geometry and the design importing the plane are reported; the fit importing the search
    and the leaf importing jit are not."""
    assert _align_broken("align.search.board", [(3, "align.fit.model")]) == [
        "3 imports align.fit.model: align.search may import only align.search, "
        f"{', '.join(_SEARCH)} of align"]
    assert len(_align_broken("align.floats", [(1, "align.jit"), (2, "align.geometry")])) == 1
    assert len(_align_broken("align.design.bound", [(5, "align.plane.fit")])) == 1
    assert _align_broken("align.fit.lsq", [(4, "align.search.result"), (5, "align.jit")]) == []
def test_nothing_below_the_command_line_imports_a_command():
    broken = []
    for path in _project_files():
        module = _module_of(path)
        for line, imported in _imports(path):
            if _within(imported, (COMMANDS,)) and not _within(module, COMMAND_IMPORTERS):
                broken.append(f"{path.relative_to(REPO)}:{line} imports {imported}: only "
                              f"{', '.join(COMMAND_IMPORTERS)} may import a command")
    assert not broken, "\n".join(broken)


def _private_uses(path: Path) -> list[tuple[int, str]]:
    """(line, ``module.name``) of each private name (a leading underscore, not a dunder) of
    another project module that the file imports (``from m import _x``) or reads through an
    imported module (``m._x``, ``import m as k; k._x``)."""
    tree = _tree(path)
    me = _module_of(path)
    modules: dict[str, str] = {}  # a name bound to a project module -> the module
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            modules.update({a.asname or a.name: a.name for a in node.names
                            if _within(a.name, PROJECT)})
        elif isinstance(node, ast.ImportFrom) and not node.level and _within(node.module or "",
                                                                              PROJECT):
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                if _is_module(sub):
                    modules[a.asname or a.name] = sub
                elif _private(a.name) and node.module != me:
                    found.append((node.lineno, sub))
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and _private(node.attr):
            chain, base = [], node.value
            while isinstance(base, ast.Attribute):
                chain.append(base.attr)
                base = base.value
            if isinstance(base, ast.Name) and base.id in modules:
                owner = ".".join([modules[base.id], *reversed(chain)])
                if _is_module(owner) and owner != me:
                    found.append((node.lineno, f"{owner}.{node.attr}"))
    return found


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _private_report(files: list[Path]) -> list[str]:
    """The private uses (file:line: what)."""
    broken = []
    for path in files:
        rel = path.relative_to(REPO).as_posix()
        for line, name in _private_uses(path):
            broken.append(f"{rel}:{line} uses {name}, private to its module: make it "
                          "public (or move it) where another module needs it")
    return broken


def test_no_module_reads_another_modules_private_names():
    """The project's code (tests aside) reaches another module only through its public names,
    so a module can be restructured behind them."""
    files = _project_files() + [f for top in TOOLS for f in sorted((REPO / top).rglob("*.py"))]
    broken = _private_report(files)
    assert not broken, "\n".join(broken)


def test_the_private_name_rule_catches_a_private_import():
    """The checker itself: both spellings of a private read are reported."""
    bad = REPO / "scenarios" / "_private_probe.py"
    bad.write_text("from scenarios.runner import _deal\nimport scenarios.store as s\n"
                   "s._real(1.0)\n", encoding="utf-8")
    try:
        broken = _private_report([bad])
        assert [b.split(" uses ")[0] for b in broken] == ["scenarios/_private_probe.py:1",
                                                          "scenarios/_private_probe.py:3"]
    finally:
        bad.unlink()


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
