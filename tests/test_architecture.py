"""The house rules of docs/architecture.md, checked on the source with ``ast`` (issue 14).

- Imports at module level. Inside a function only (a) an optional dependency
  (:data:`OPTIONAL_DEPENDENCIES`) or (b) in a module that calls ``_compile.interpret_kernels()``,
  a kinefuse module that loads compiled kernels: the switch to interpreted kernels must run before
  any kernel module is imported, so that lazy path stays (with a comment saying so).
- A module has at most :data:`MAX_MODULE_LINES` lines, unless its docstring contains
  :data:`LONG_MODULE_MARKER` followed by the reason (e.g. a compiled-kernel file whose kernels
  must share one module so numba can inline them).
- A public function or method (name without a leading ``_``) has at most
  :data:`MAX_FUNCTION_LINES` lines of code: from ``def`` to its last line, the docstring not
  counted (numpydoc docstrings with shapes, units and deviations are wanted, not penalised).

Ratchet: the redesign is merged branch by branch, so today's violations are listed below by
name. A violation not in a list fails; a list entry that is no longer a violation fails too, so
the lists only shrink. When a test fails it prints what to add (never do that for new code) or
what to remove.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass

from conftest import REPO_ROOT
from kinefuse._compile import KERNEL_MODULES

SRC = REPO_ROOT / "src"
PACKAGE = SRC / "kinefuse"

MAX_MODULE_LINES = 700
MAX_FUNCTION_LINES = 80
LONG_MODULE_MARKER = "compiled-kernel module:"

#: Optional dependencies (extras in pyproject.toml, or a system installation): imported where
#: they are used so that kinefuse works without them.
OPTIONAL_DEPENDENCIES = frozenset(
    {
        "pylsl",  # [lsl]
        "dask",  # [batch]
        "distributed",  # [batch]
        "pyarrow",  # [batch]
        "playwright",  # tests / live-view browser checks
        "opensim",  # conda-only OpenSim bindings
        "ezc3d",  # [c3d]
        "filterpy",  # [bench]: the peer of `kinefuse bench`
    }
)

# ---- ratchet: the violations left after the redesign merge (issue 14); remove entries as they
# are fixed.

#: ``path::function -> imported module`` for imports inside functions.
ALLOWED_FUNCTION_IMPORTS: frozenset[str] = frozenset()

#: Modules above MAX_MODULE_LINES without a stated reason.
ALLOWED_LONG_MODULES: frozenset[str] = frozenset()

#: ``path::qualified.name`` of public functions above MAX_FUNCTION_LINES lines of code.
ALLOWED_LONG_FUNCTIONS: frozenset[str] = frozenset()


# ---- the source model ------------------------------------------------------------------------


@dataclass(frozen=True)
class Module:
    name: str  # dotted, e.g. kinefuse.filters.kalman
    rel: str  # path relative to src/, e.g. kinefuse/filters/kalman.py
    tree: ast.Module
    n_lines: int
    is_package: bool


def _modules() -> dict[str, Module]:
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(SRC).as_posix()
        parts = rel[: -len(".py")].split("/")
        is_package = parts[-1] == "__init__"
        if is_package:
            parts = parts[:-1]
        text = path.read_text(encoding="utf-8")
        tree = ast.parse(text, filename=rel)
        out[".".join(parts)] = Module(
            ".".join(parts), rel, tree, len(text.splitlines()), is_package
        )
    return out


MODULES = _modules()


def _absolute(module: Module, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = module.name.split(".")
    if not module.is_package:
        base = base[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _targets(module: Module, node: ast.Import | ast.ImportFrom) -> list[str]:
    """Modules an import statement names (``from a import b`` names ``a`` and ``a.b`` if a module)."""
    if isinstance(node, ast.Import):
        return [alias.name for alias in node.names]
    base = _absolute(module, node)
    subs = [f"{base}.{alias.name}" for alias in node.names if f"{base}.{alias.name}" in MODULES]
    return [base, *subs]


def _is_type_checking(node: ast.If) -> bool:
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _module_level_imports(module: Module) -> list[ast.Import | ast.ImportFrom]:
    """Imports that run when the module is imported (not in functions, not TYPE_CHECKING-only)."""
    found: list[ast.Import | ast.ImportFrom] = []

    def visit(body):
        for node in body:
            if isinstance(node, ast.Import | ast.ImportFrom):
                found.append(node)
            elif isinstance(node, ast.If) and _is_type_checking(node):
                visit(node.orelse)
            elif isinstance(node, ast.If | ast.Try | ast.With | ast.ClassDef):
                for field in ("body", "orelse", "finalbody", "handlers"):
                    for child in getattr(node, field, []):
                        visit(child.body if isinstance(child, ast.ExceptHandler) else [child])

    visit(module.tree.body)
    return found


def _with_parents(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[: i + 1]) for i in range(len(parts))]


def _loads_kernels() -> set[str]:
    """kinefuse modules whose import (at module level, transitively) imports a kernel module."""
    edges: dict[str, set[str]] = {}
    for module in MODULES.values():
        deps = set()
        for node in _module_level_imports(module):
            for target in _targets(module, node):
                deps.update(p for p in _with_parents(target) if p in MODULES)
        edges[module.name] = deps
    loads = set(KERNEL_MODULES)
    changed = True
    while changed:
        changed = False
        for name, deps in edges.items():
            if name not in loads and deps & loads:
                loads.add(name)
                changed = True
    return loads


def _function_imports(module: Module):
    """(qualified function name, import node) for every import inside a function body."""

    def visit(node, qual, in_function):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef):
                yield from visit(child, f"{qual}{child.name}.", True)
            elif isinstance(child, ast.ClassDef):
                yield from visit(child, f"{qual}{child.name}.", in_function)
            elif isinstance(child, ast.Import | ast.ImportFrom) and in_function:
                yield qual.rstrip("."), child
            else:
                yield from visit(child, qual, in_function)

    yield from visit(module.tree, "", False)


def _calls_interpret_kernels(module: Module) -> bool:
    return any(
        isinstance(node, ast.Call)
        and (
            (isinstance(node.func, ast.Attribute) and node.func.attr == "interpret_kernels")
            or (isinstance(node.func, ast.Name) and node.func.id == "interpret_kernels")
        )
        for node in ast.walk(module.tree)
    )


def _public_functions(module: Module):
    """(qualified name, lines of code without the docstring) of public functions and methods."""

    def visit(body, qual):
        for node in body:
            if isinstance(node, ast.ClassDef):
                yield from visit(node.body, f"{qual}{node.name}.")
            elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                if node.name.startswith("_"):
                    continue
                n = node.end_lineno - node.lineno + 1
                doc = node.body[0]
                if (
                    isinstance(doc, ast.Expr)
                    and isinstance(doc.value, ast.Constant)
                    and isinstance(doc.value.value, str)
                ):
                    n -= doc.end_lineno - doc.lineno + 1
                yield f"{qual}{node.name}", n

    yield from visit(module.tree.body, "")


# ---- the checks --------------------------------------------------------------------------------


def function_import_violations() -> set[str]:
    kernel_loaders = _loads_kernels()
    out = set()
    for module in MODULES.values():
        gate = _calls_interpret_kernels(module)
        for qual, node in _function_imports(module):
            targets = _targets(module, node)
            if all(t.split(".")[0] in OPTIONAL_DEPENDENCIES for t in targets):
                continue
            if gate and any(p in kernel_loaders for t in targets for p in _with_parents(t)):
                continue  # behind _compile.interpret_kernels (see the module's comment)
            named = ", ".join(targets[1:] or targets)  # `from a import b`: a.b if a module
            out.add(f"{module.rel}::{qual} -> {named}")
    return out


def long_module_violations() -> set[str]:
    out = set()
    for module in MODULES.values():
        if module.n_lines <= MAX_MODULE_LINES:
            continue
        doc = ast.get_docstring(module.tree) or ""
        if LONG_MODULE_MARKER not in doc:
            out.add(module.rel)
    return out


def long_function_violations() -> set[str]:
    return {
        f"{module.rel}::{qual}"
        for module in MODULES.values()
        for qual, n in _public_functions(module)
        if n > MAX_FUNCTION_LINES
    }


def _ratchet(found: set[str], allowed: frozenset[str], what: str, name: str) -> None:
    new = sorted(found - allowed)
    fixed = sorted(allowed - found)
    lines = []
    if new:
        lines.append(f"{len(new)} new {what} (fix them; see docs/architecture.md):")
        lines += [f"    {v!r}," for v in new]
    if fixed:
        lines.append(f"{len(fixed)} entries of {name} are no longer violations; remove them:")
        lines += [f"    {v!r}," for v in fixed]
    assert not lines, "\n".join(lines)


def test_imports_inside_functions_only_for_optional_dependencies():
    _ratchet(
        function_import_violations(),
        ALLOWED_FUNCTION_IMPORTS,
        "imports inside functions",
        "ALLOWED_FUNCTION_IMPORTS",
    )


def test_modules_at_most_700_lines_unless_they_say_why():
    _ratchet(
        long_module_violations(),
        ALLOWED_LONG_MODULES,
        f"modules above {MAX_MODULE_LINES} lines without {LONG_MODULE_MARKER!r} in the docstring",
        "ALLOWED_LONG_MODULES",
    )


def test_public_functions_at_most_80_lines():
    _ratchet(
        long_function_violations(),
        ALLOWED_LONG_FUNCTIONS,
        f"public functions above {MAX_FUNCTION_LINES} lines of code",
        "ALLOWED_LONG_FUNCTIONS",
    )


# ---- the checker checks itself on small sources ---------------------------------------------


def _fake(name: str, source: str, is_package: bool = False) -> Module:
    tree = ast.parse(source)
    rel = name.replace(".", "/") + ("/__init__.py" if is_package else ".py")
    return Module(name, rel, tree, len(source.splitlines()), is_package)


def test_checker_sees_nested_and_relative_imports():
    mod = _fake(
        "kinefuse.pkg.mod",
        "import os\n"
        "def f():\n"
        "    from . import sibling\n"
        "    class C:\n"
        "        def g(self):\n"
        "            import pylsl\n"
        "class K:\n"
        "    def m(self):\n"
        "        from ..io import load\n",
    )
    found = [(q, _targets(mod, n)[0]) for q, n in _function_imports(mod)]
    assert found == [("f", "kinefuse.pkg"), ("f.C.g", "pylsl"), ("K.m", "kinefuse.io")]


def test_checker_counts_code_lines_without_the_docstring():
    body = "\n".join(f"    x{i} = {i}" for i in range(3))
    mod = _fake(
        "kinefuse.m", f'def f():\n    """Doc.\n\n    More.\n    """\n{body}\ndef _g():\n    pass\n'
    )
    assert list(_public_functions(mod)) == [("f", 4)]


def test_checker_ignores_type_checking_imports():
    mod = _fake(
        "kinefuse.m",
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import kinefuse.x\nelse:\n"
        "    import kinefuse.y\n",
    )
    names = [_targets(mod, n)[0] for n in _module_level_imports(mod)]
    assert names == ["typing", "kinefuse.y"]
