"""The shape of the code base (issue #14): one-way imports, no god files or functions.

Imports are read from the source with `ast`, function-level imports included (an import hidden
in a function is still a dependency); imports under `if TYPE_CHECKING:` are annotations only
and never run, so they are left out.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# source folder -> the package name it installs as (setup.py's package_dir)
PACKAGES = {
    "fastenerf": ROOT / "fastenerf",
    "fastenerf.kernels": ROOT / "kernels",
    "fastenerf.viewer": ROOT / "viewer",
    "benchmarks": ROOT / "benchmarks",
}
MAX_FILE_LINES = 600
MAX_FUNCTION_LINES = 80


def source_files() -> dict[str, Path]:
    """module name -> file, for every .py file of the packages (links not followed)."""
    mods: dict[str, Path] = {}
    for pkg, folder in PACKAGES.items():
        for path in sorted(folder.rglob("*.py")):
            rel = path.relative_to(folder)
            if any(part in ("kernels", "viewer") for part in rel.parts[:-1]) and pkg == "fastenerf":
                continue  # the git-ignored links fastenerf/kernels, fastenerf/viewer
            parts = list(rel.with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            mods[".".join([pkg, *parts])] = path
    return mods


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING"
    )


def imports_of(module: str, path: Path, known: set[str]) -> set[str]:
    """The known modules `module` imports (absolute or relative, at any depth in the file)."""
    tree = ast.parse(path.read_text(), str(path))
    is_pkg = path.name == "__init__.py"
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and _is_type_checking(node):
            skip.update(id(n) for b in node.body for n in ast.walk(b))
    out: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base if is_pkg else base[:-1]
                base = base[: len(base) - (node.level - 1)]
                stem = ".".join(base + ([node.module] if node.module else []))
            else:
                stem = node.module or ""
            names = [stem] + [f"{stem}.{a.name}" for a in node.names]
        for n in names:
            while n and n not in known:
                n = n.rpartition(".")[0]
            if n and n != module:
                out.add(n)
    return out


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle as a list of modules, or None (iterative DFS, colours)."""
    colour = dict.fromkeys(graph, 0)
    for start in graph:
        if colour[start]:
            continue
        stack = [(start, iter(sorted(graph[start])))]
        path = [start]
        colour[start] = 1
        while stack:
            node, it = stack[-1]
            nxt = next(it, None)
            if nxt is None:
                colour[node] = 2
                stack.pop()
                path.pop()
            elif colour[nxt] == 1:
                return path[path.index(nxt) :] + [nxt]
            elif colour[nxt] == 0:
                colour[nxt] = 1
                stack.append((nxt, iter(sorted(graph[nxt]))))
                path.append(nxt)
    return None


def test_cycle_finder_finds_a_planted_cycle():
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert find_cycle(g) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_relative_imports_resolve(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("from ..x import y\nfrom . import z\n\ndef g():\n    from .w import v\n")
    known = {"p.x", "p.x.y", "p.q.z", "p.q.w", "p.q.m"}
    assert imports_of("p.q.m", f, known) == {"p.x", "p.x.y", "p.q.z", "p.q.w"}


def test_no_import_cycle():
    mods = source_files()
    known = set(mods)
    graph = {m: imports_of(m, p, known) for m, p in mods.items()}
    # a package imports its submodules to re-export them: the parent -> child edge is the
    # package's own face, not a dependency of a lower module on a higher one
    graph = {m: {d for d in deps if not d.startswith(m + ".")} for m, deps in graph.items()}
    assert find_cycle(graph) is None, " -> ".join(find_cycle(graph))


def test_no_file_over_the_limit():
    long = {
        str(p.relative_to(ROOT)): n
        for p in source_files().values()
        if (n := len(p.read_text().splitlines())) > MAX_FILE_LINES
    }
    assert not long, long


def test_no_function_over_the_limit_outside_kernels():
    long = {}
    for mod, path in source_files().items():
        if mod.startswith("fastenerf.kernels"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long[f"{path.relative_to(ROOT)}:{node.lineno} {node.name}"] = n
    assert not long, long


def test_benchmarks_never_step_the_trainer():
    for path in PACKAGES["benchmarks"].rglob("*.py"):
        tree = ast.parse(path.read_text())
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Attribute)
                and node.func.attr == "step"
            ):
                raise AssertionError(f"{path.name}:{node.lineno} calls .step()")
