"""The package's modules import each other without cycles: none among the imports at the top of
the modules, and no import inside a function that would close one (an import hidden in a function
only to break a cycle). Importing ``a.b.c`` imports the packages ``a`` and ``a.b`` too, so those
count; imports under ``if TYPE_CHECKING:`` do not (they never run).
"""

from __future__ import annotations

import ast
import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _modules() -> dict[str, Path]:
    """Module name -> file of every module of ``haptic_collab`` (through its folder links)."""
    out = {}
    for folder, dirs, files in os.walk(ROOT / "haptic_collab", followlinks=True):
        dirs[:] = [d for d in dirs if d not in ("node_modules", "__pycache__")]
        for file in files:
            if not file.endswith(".py"):
                continue
            path = Path(folder) / file
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _graphs(mods: dict[str, Path]) -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    """(imports at module level, imports inside functions): module -> modules it imports."""

    def owner(name: str) -> str | None:  # the module a dotted name is, or lives in
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    top: dict[str, set[str]] = {m: set() for m in mods}
    inner: dict[str, set[str]] = {m: set() for m in mods}

    def visit(mod: str, node: ast.AST, in_function: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                continue
            names: list[str] = []
            if isinstance(child, ast.Import):
                names = [a.name for a in child.names]
            elif isinstance(child, ast.ImportFrom) and child.module:
                base = child.module
                if child.level:
                    base = ".".join(mod.split(".")[: -child.level] + [base])
                names = [base] + [f"{base}.{a.name}" for a in child.names]
            for name in names:
                target = owner(name)
                if target is None or target == mod:
                    continue
                parts = target.split(".")
                for i in range(2, len(parts) + 1):  # the packages on the way are imported too
                    step = ".".join(parts[:i])
                    if step in mods and step != mod and not mod.startswith(step + "."):
                        (inner if in_function else top)[mod].add(step)
            nested = in_function or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef)
            visit(mod, child, nested)

    for mod, path in mods.items():
        visit(mod, ast.parse(path.read_text(encoding="utf-8")), False)
    return top, inner


def _reaches(graph: dict[str, set[str]], start: str, goal: str) -> bool:
    seen: set[str] = set()
    stack = [start]
    while stack:
        m = stack.pop()
        if m == goal:
            return True
        if m not in seen:
            seen.add(m)
            stack.extend(graph[m])
    return False


def test_no_module_imports_itself_back():
    mods = _modules()
    assert "haptic_collab.shared.protocol" in mods and "haptic_collab.client.session" in mods
    top, inner = _graphs(mods)
    cycles = [f"{a} -> {b}" for a in top for b in top[a] if _reaches(top, b, a)]
    assert cycles == [], cycles
    hidden = [f"{a} -> {b}" for a in inner for b in inner[a] if _reaches(top, b, a)]
    assert hidden == [], f"function-level imports that close a cycle: {hidden}"


def test_the_check_sees_a_cycle_hidden_in_a_function(tmp_path):
    (tmp_path / "a.py").write_text("from pkg.b import f\n")
    (tmp_path / "b.py").write_text("def f():\n    from pkg.a import g\n    return g\n")
    (tmp_path / "c.py").write_text("import pkg.a\nimport pkg.b\n")
    mods = {f"pkg.{n}": tmp_path / f"{n}.py" for n in "abc"}
    top, inner = _graphs(mods)
    assert top == {"pkg.a": {"pkg.b"}, "pkg.b": set(), "pkg.c": {"pkg.a", "pkg.b"}}
    assert inner["pkg.b"] == {"pkg.a"} and _reaches(top, "pkg.a", "pkg.b")


RUNTIME = ("server", "client", "shared", "web")


def test_the_runtime_imports_nothing_from_the_tools_around_it():
    """server/, client/, shared/ and web/ (what a deployment runs) import nothing of
    haptic_collab's own modules around them (the CLI, the benchmarks, the research drivers, the
    demo), at module level or inside a function; shared/ imports neither server/ nor client/."""
    mods = _modules()
    top, inner = _graphs(mods)
    runtime = {m for m in mods if m.split(".")[1:2] and m.split(".")[1] in RUNTIME}
    assert (
        "haptic_collab.client.workers" in runtime and "haptic_collab.shared.gains.choose" in runtime
    )
    outside = [
        f"{a} -> {b}"
        for a in sorted(runtime)
        for b in sorted(top[a] | inner[a])
        if b != "haptic_collab" and b not in runtime
    ]
    assert outside == [], outside
    upward = [
        f"{a} -> {b}"
        for a in sorted(runtime)
        if a.startswith("haptic_collab.shared")
        for b in sorted(top[a] | inner[a])
        if b.startswith(("haptic_collab.server", "haptic_collab.client"))
    ]
    assert upward == [], upward
