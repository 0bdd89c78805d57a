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


# --- nothing outside io/ branches on the input's kind (issue 30, item 1) -----------------------

def _input_kinds() -> set[str]:
    """Every kind io/ gives a source: the str constants assigned to a `kind` or `KIND` (also in
    a tuple assignment, `kind, topic = "rosbag", None`) anywhere in lidar_slam/io."""
    kinds = set()
    for f in (PKG / "io").rglob("*.py"):
        for node in ast.walk(ast.parse(f.read_text())):
            if not isinstance(node, ast.Assign):
                continue
            values = node.value.elts if isinstance(node.value, ast.Tuple) else [node.value]
            for target in node.targets:
                names = target.elts if isinstance(target, ast.Tuple) else [target]
                for name, value in zip(names, values):
                    ident = name.id if isinstance(name, ast.Name) else \
                        name.attr if isinstance(name, ast.Attribute) else None
                    if ident in ("kind", "KIND") and isinstance(value, ast.Constant) \
                            and isinstance(value.value, str):
                        kinds.add(value.value)
    return kinds


def _is_kind(node: ast.AST) -> bool:
    """`x.kind`, `x.input_kind`, `x["kind"]`, `x["input_kind"]`, or a name `kind`, `input_kind`."""
    if isinstance(node, ast.Attribute):
        return node.attr in ("kind", "input_kind")
    if isinstance(node, ast.Subscript):
        return isinstance(node.slice, ast.Constant) and node.slice.value in ("kind", "input_kind")
    return isinstance(node, ast.Name) and node.id in ("kind", "input_kind")


def _of_a_source(node: ast.AST) -> bool:
    """`source.kind`, `src.kind`, `self.source.kind`...: the kind of an input, whatever it is
    compared with."""
    if not (isinstance(node, ast.Attribute) and node.attr == "kind"):
        return False
    owner = node.value
    name = owner.id if isinstance(owner, ast.Name) else \
        owner.attr if isinstance(owner, ast.Attribute) else ""
    return "source" in name or name in ("src", "data", "dataset", "bag", "pcap")


def _names_a_kind(node: ast.AST, kinds: set[str]) -> bool:
    if isinstance(node, ast.Constant):
        return node.value in kinds
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return any(_names_a_kind(e, kinds) for e in node.elts)
    return False


def _kind_branches(tree: ast.AST, kinds: set[str]) -> list[int]:
    """Lines that branch on an input's kind: a comparison (==, !=, in, not in, ...) of a source's
    kind, or of any kind with an input kind's name; a `match` on a kind; an isinstance check
    against a source class (`...Source`). Reporting it (summary.json's input_kind, a message)
    is not branching."""
    lines = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Compare):
            operands = [node.left, *node.comparators]
            if any(_of_a_source(o) for o in operands) or (
                    any(_is_kind(o) for o in operands)
                    and any(_names_a_kind(o, kinds) for o in operands)):
                lines.append(node.lineno)
        elif isinstance(node, ast.Match) and _is_kind(node.subject):
            lines.append(node.lineno)
        elif isinstance(node, ast.Call) and isinstance(node.func, ast.Name) \
                and node.func.id == "isinstance" and len(node.args) == 2:
            classes = node.args[1].elts if isinstance(node.args[1], ast.Tuple) else [node.args[1]]
            if any(isinstance(c, (ast.Name, ast.Attribute)) and
                   (c.id if isinstance(c, ast.Name) else c.attr).endswith("Source")
                   for c in classes):
                lines.append(node.lineno)
    return lines


def test_the_rule_sees_the_branches_it_forbids():
    kinds = _input_kinds()
    assert {"folder", "file", "kitti", "kitti_raw", "rosbag", "ouster_pcap", "velodyne_pcap",
            "newer_college", "mulran", "nclt", "kitti360", "boreas"} <= kinds, kinds
    branching = ['stamps = source.stamps if source.kind != "file" else None',
                 'is_bag = kind == "rosbag"', 'if src.kind in ("mulran", "nclt"): pass',
                 'ok = summary["input_kind"] not in {"kitti"}',
                 'if isinstance(source, RosbagSource): pass',
                 'match source.kind:\n    case "kitti": pass']
    for code in branching:
        assert _kind_branches(ast.parse(code), kinds) == [1], code
    reporting = ['info = {"input_kind": source.kind}', 'msg = f"a {source.kind} input"',
                 'if phase.kind == "walk": pass', 'if site.kind != "outdoor": pass']
    for code in reporting:
        assert _kind_branches(ast.parse(code), kinds) == [], code


def test_nothing_outside_io_branches_on_the_input_kind():
    """The source open_source returns owns every stream of its input (scans, stamps, IMU,
    GNSS, ground truth), so a new input format is one module in io/ plus its tests."""
    kinds = _input_kinds()
    offenders = {}
    for f in sorted(PKG.rglob("*.py")):
        if f.relative_to(PKG).parts[0] == "io":
            continue
        lines = _kind_branches(ast.parse(f.read_text()), kinds)
        if lines:
            offenders[str(f.relative_to(PKG.parent))] = lines
    assert offenders == {}, offenders
