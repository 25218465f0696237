"""align's compiled kernels call across modules only into the leaf, and none is a hand copy.

numba's cache keys a kernel on its own file: a kernel that calls a kernel of another module
keeps its cached machine code when that other kernel changes (align/jit.py stamps every cache
with the leaf, align/floats.py, so the leaf alone may be called from anywhere). The way round
this used to be copies of a kernel in each file that called it; a copy drifts. So: every
function compiled by numba in align/ (decorated with `align.jit.kernel`, numba's `njit` or
`intrinsic`) calls, of the names it imports from other align modules, only align.floats's; and
no two of them have the same body.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

ALIGN = Path(__file__).resolve().parents[1] / "align"
LEAF = "align.floats"
#: The decorators that make a function a numba kernel.
KERNEL_DECORATORS = {"kernel", "njit", "jit", "intrinsic", "generated_jit", "vectorize"}


def _module_name(path: Path) -> str:
    parts = path.relative_to(ALIGN.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _resolve(module: str, node: ast.ImportFrom) -> str:
    """The absolute module an ``from ... import`` names (relative imports resolved)."""
    if not node.level:
        return node.module or ""
    base = module.split(".")[: -node.level]
    return ".".join(base + ([node.module] if node.module else []))


def _imported(module: str, tree: ast.Module) -> tuple[dict[str, str], dict[str, str]]:
    """The module's names taken from other align modules: {name: its module} for functions
    and the like, {alias: module} for align modules imported whole."""
    names, modules = {}, {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            src = _resolve(module, node)
            if not (src == "align" or src.startswith("align.")):
                continue
            for a in node.names:
                full = f"{src}.{a.name}"
                if (ALIGN.parent / Path(*full.split("."))).with_suffix(".py").exists() or (
                        ALIGN.parent / Path(*full.split("."))).is_dir():
                    modules[a.asname or a.name] = full  # a module: `from align.x import y`
                elif src != module:
                    names[a.asname or a.name] = src
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("align.") and a.name != module:
                    # `import align.x as y` binds y; `import align.x`: calls read align.x.f
                    modules[a.asname or a.name] = a.name
    return names, modules


def _decorator_name(dec: ast.expr) -> str:
    if isinstance(dec, ast.Call):
        dec = dec.func
    if isinstance(dec, ast.Attribute):
        return dec.attr
    return dec.id if isinstance(dec, ast.Name) else ""


def _kernels(tree: ast.Module) -> list[ast.FunctionDef]:
    return [node for node in ast.walk(tree) if isinstance(node, ast.FunctionDef)
            and any(_decorator_name(d) in KERNEL_DECORATORS for d in node.decorator_list)]


def _dotted(node: ast.expr) -> str | None:
    """``a.b.c`` of an attribute chain on a name, else None."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name):
        return None
    return ".".join([node.id, *reversed(parts)])


def _callee_module(call: ast.Call, names: dict[str, str], modules: dict[str, str]
                   ) -> str | None:
    """The align module a call's function comes from, when another module's; else None."""
    func = call.func
    if isinstance(func, ast.Name):
        return names.get(func.id)
    dotted = _dotted(func)
    if dotted is None:
        return None
    head, _, _ = dotted.rpartition(".")
    for alias, full in modules.items():
        if head == alias:
            return full
        if head.startswith(alias + "."):  # `import align.x` then align.x.y.f()
            return f"{full}{head[len(alias):]}"
    return None


def _calls(fn: ast.FunctionDef) -> list[ast.Call]:
    """The calls in a function's body (not its decorators')."""
    return [c for stmt in fn.body for c in ast.walk(stmt) if isinstance(c, ast.Call)]


@functools.cache
def _sources() -> list[tuple[Path, str, ast.Module]]:
    out = []
    for path in sorted(ALIGN.rglob("*.py")):
        out.append((path, _module_name(path), ast.parse(path.read_text(), filename=str(path))))
    return out


def test_kernels_call_other_modules_only_through_the_leaf():
    sources = _sources()
    assert sum(len(_kernels(tree)) for _, _, tree in sources) > 100  # the kernels were found
    bad = []
    for path, module, tree in sources:
        names, modules = _imported(module, tree)
        for fn in _kernels(tree):
            for node in _calls(fn):
                src = _callee_module(node, names, modules)
                if src is not None and src != module and src != LEAF:
                    bad.append(f"{path.relative_to(ALIGN.parent)}:{node.lineno}: kernel "
                               f"{fn.name} calls {ast.unparse(node.func)} of {src} (only "
                               f"{LEAF}'s may be called from another module)")
    assert bad == [], "\n".join(bad)


def _body_text(fn: ast.FunctionDef) -> str:
    """The function's body without its docstring, as source (layout and comments dropped)."""
    body = fn.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) \
            and isinstance(body[0].value.value, str):
        body = body[1:]
    return "\n".join(ast.unparse(s) for s in body)


def test_no_kernel_is_a_hand_copy_of_another():
    seen: dict[str, str] = {}
    copies = []
    for path, _, tree in _sources():
        for fn in _kernels(tree):
            text = _body_text(fn)
            where = f"{path.relative_to(ALIGN.parent)}:{fn.lineno} {fn.name}"
            if text in seen:
                copies.append(f"{where} has the body of {seen[text]}")
            else:
                seen[text] = where
    assert copies == [], "\n".join(copies)


def test_the_checks_see_a_call_across_modules_and_a_copy():
    """The two checks above on a made-up pair of modules: a kernel calling another module's
    kernel is named, one calling the leaf is not; a copy is found."""
    src = ("from align.floats import fma\nfrom align.plane.kernels import lsq_plane\n"
           "from align.jit import kernel\n\n@kernel\ndef f(a):\n    return fma(a, a, a)\n\n"
           "@kernel(error_model='numpy')\ndef g(a):\n    return lsq_plane(a)\n\n"
           "@kernel\ndef h(a):\n    '''doc'''\n    return fma(a, a, a)\n")
    tree = ast.parse(src)
    names, modules = _imported("align.fit.made_up", tree)
    calls = {fn.name: [_callee_module(c, names, modules) for c in _calls(fn)]
             for fn in _kernels(tree)}
    assert calls == {"f": [LEAF], "g": ["align.plane.kernels"], "h": [LEAF]}
    f, _, h = _kernels(tree)
    assert _body_text(f) == _body_text(h)
