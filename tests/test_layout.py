"""The package's layout rules (issue 24): no import circle between its modules, typer only in
the CLI, each CLI module short, and one home for each shared helper."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "lidar_slam"


def _module_name(path: Path) -> str:
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, modules: set[str]) -> set[str]:
    """The package modules a file imports, at any depth of the file (function-level imports
    included: a circle through them is still a circle)."""
    tree = ast.parse(path.read_text())
    here = _module_name(path)
    found = set()
    for node in ast.walk(tree):
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        for name in names:
            if name in modules and name != here:
                found.add(name)
    return found


def _graph() -> dict[str, set[str]]:
    files = sorted(PKG.rglob("*.py"))
    modules = {_module_name(f) for f in files}
    return {_module_name(f): _imports(f, modules) for f in files}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    sys.setrecursionlimit(10000)
    for v in graph:
        if v not in index:
            visit(v)
    return out


def _ignoring_package_inits(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """A package's __init__ that re-exports its modules is not a circle with them."""
    packages = {m for m in graph if (PKG.parent / m.replace(".", "/") / "__init__.py").is_file()}
    return {m: {d for d in deps if not (m in packages and d.startswith(m + "."))}
            for m, deps in graph.items()}


def test_no_import_circle_between_the_package_modules():
    cycles = _cycles(_ignoring_package_inits(_graph()))
    assert cycles == [], cycles


def test_only_the_cli_imports_typer():
    offenders = [str(f.relative_to(PKG.parent)) for f in PKG.rglob("*.py")
                 if "cli" not in f.relative_to(PKG).parts[:1]
                 and any(isinstance(n, (ast.Import, ast.ImportFrom)) and any(
                     (getattr(n, "module", None) or a.name).split(".")[0] == "typer"
                     for a in n.names) for n in ast.walk(ast.parse(f.read_text())))]
    assert offenders == []
    code = ("import sys, lidar_slam.run, lidar_slam.batch, lidar_slam.sim, lidar_slam.pipeline\n"
            "assert 'typer' not in sys.modules, 'typer imported'")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_each_cli_module_is_short():
    sizes = {f.name: len(f.read_text().splitlines()) for f in (PKG / "cli").glob("*.py")}
    assert max(sizes.values()) < 250, sizes


def test_one_home_for_each_shared_helper():
    """One atomic writer, one PLY writer, one voxel downsampler, one small_gicp wrapper."""
    def defining(pattern: str) -> list[str]:
        return sorted(str(f.relative_to(PKG)) for f in PKG.rglob("*.py")
                      if pattern in f.read_text())

    assert defining("os.replace(") == ["io/atomic.py"]
    assert defining("def write_ply") == ["io/ply.py"]
    assert defining("def voxel_downsample") == ["frontend/downsample.py"]
    assert defining("import small_gicp") == ["registration.py"]
