"""The house rules of docs/architecture.md, checked on the source.

- imports run down the floors (a room imports rooms on its own floor or below), never up;
- no import cycle between modules, counting imports made inside functions;
- ``stages`` never imports ``vet_cli``;
- no module in ``stages/`` or ``vet_cli/`` is over 600 lines.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# Each room of ``stages`` (its top-level module or package) and its floor. A room imports
# rooms of its own floor or lower. docs/architecture.md describes the same table.
FLOORS = {
    # 0: data, physics and file formats: what everything else stands on
    "errors": 0,
    "cluster": 0,
    "provenance": 0,
    "rig": 0,
    "physics": 0,
    "crossings": 0,
    "optics": 0,
    "measure_grid": 0,
    "formats": 0,
    "motion": 0,
    "scenes": 0,
    "metrics": 0,
    "falsecolor": 0,
    "tonemap": 0,
    # 1: the methods and the device drivers
    "simulate": 1,
    "hdr_static": 1,
    "flow": 1,
    "burst": 1,
    "deblur": 1,
    "devices": 1,
    # 2: workflows that combine methods and devices
    "capture": 2,
    "calibrate": 2,
    "evaluate": 2,
    "batch": 2,
    "info": 2,
    "sample_data": 2,
}
CLI_FLOOR = 3
MAX_LINES = 600


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in ("stages", "vet_cli"):
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _resolve(name: str, known: dict[str, Path]) -> str | None:
    """The longest known module that ``name`` (a dotted import target) lies in."""
    parts = name.split(".")
    while parts:
        candidate = ".".join(parts)
        if candidate in known:
            return candidate
        parts.pop()
    return None


def _imports(module: str, path: Path, known: dict[str, Path]) -> set[str]:
    """Every project module ``module`` imports, wherever in the file the import is."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    is_pkg = path.name == "__init__.py"
    package = module if is_pkg else module.rpartition(".")[0]
    found = set()
    for node in ast.walk(tree):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                if node.level > 1:
                    base = base[: -(node.level - 1)]
                prefix = ".".join(base)
                mod = f"{prefix}.{node.module}" if node.module else prefix
            else:
                mod = node.module or ""
            # ``from pkg import mod`` depends on pkg.mod; on pkg itself only for its names
            subs = [f"{mod}.{a.name}" for a in node.names]
            deeper = [t for t in subs if _resolve(t, known) not in (None, _resolve(mod, known))]
            targets = deeper if len(deeper) == len(subs) else subs + [mod]
        for target in targets:
            hit = _resolve(target, known)
            if hit and hit != module:
                found.add(hit)
    return found


def _graph() -> dict[str, set[str]]:
    known = _modules()
    return {m: _imports(m, p, known) for m, p in known.items()}


def _room(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if parts[0] == "stages" and len(parts) > 1 else None


def _floor(module: str) -> int | None:
    if module.startswith("vet_cli"):
        return CLI_FLOOR
    room = _room(module)
    return FLOORS.get(room) if room else -1  # the ``stages`` package itself: the ground


def test_every_room_has_a_floor():
    rooms = {_room(m) for m in _modules()} - {None}
    missing = sorted(r for r in rooms if r not in FLOORS)
    assert not missing, f"rooms without a floor in FLOORS (and docs/architecture.md): {missing}"


def test_imports_run_down_the_floors():
    upward = []
    for module, deps in _graph().items():
        for dep in deps:
            floor, dep_floor = _floor(module), _floor(dep)
            if None in (floor, dep_floor):
                continue
            if dep_floor > floor:
                upward.append(f"{module} (floor {floor}) imports {dep} (floor {dep_floor})")
    assert not upward, "\n".join(upward)


def test_no_import_cycles():
    graph = _graph()
    # Tarjan's strongly connected components; any component of two or more is a cycle.
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    # A package's __init__ re-exporting its own modules is not a cycle between rooms, as
    # long as the modules do not import the package back.
    assert not cycles, f"import cycles: {cycles}"


@pytest.mark.parametrize("pkg", ["stages", "vet_cli"])
def test_no_module_is_oversized(pkg):
    long = []
    for path in sorted((ROOT / pkg).rglob("*.py")):
        n = len(path.read_text(encoding="utf-8").splitlines())
        if n > MAX_LINES:
            long.append(f"{path.relative_to(ROOT)}: {n} lines")
    assert not long, "\n".join(long)


def test_known_answer_cycle_detection(tmp_path):
    """The resolver sees relative and in-function imports (the forms cycles hide in)."""
    pkg = tmp_path / "stages" / "formats"
    pkg.mkdir(parents=True)
    (tmp_path / "stages" / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from .b import x\n")
    (pkg / "b.py").write_text("def f():\n    from stages.formats import a\n")
    known = {
        "stages.formats.a": pkg / "a.py",
        "stages.formats.b": pkg / "b.py",
        "stages.formats": pkg / "__init__.py",
        "stages": tmp_path / "stages" / "__init__.py",
    }
    assert _imports("stages.formats.a", pkg / "a.py", known) == {"stages.formats.b"}
    assert _imports("stages.formats.b", pkg / "b.py", known) == {"stages.formats.a"}


#: Figures a docstring may hold: constants and format examples, not measurements.
ALLOWED_FIGURES = {"0.2126", "0.7152", "0.0722", "0.0075"}


def benchmark_figures() -> list[str]:
    """Docstring lines of stages/ and vet_cli/ holding a number with three or more
    decimals (a measured figure, which goes stale with every commit) other than the
    allowed constants."""
    found = []
    for pkg in ("stages", "vet_cli"):
        for path in sorted((ROOT / pkg).rglob("*.py")):
            tree = ast.parse(path.read_text(encoding="utf-8"))
            for node in ast.walk(tree):
                if not isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef):
                    continue
                doc = ast.get_docstring(node, clean=False) or ""
                for line in doc.splitlines():
                    numbers = set(re.findall(r"\d+\.\d{3,}", line)) - ALLOWED_FIGURES
                    if numbers or re.search(r"times faster|x faster", line):
                        found.append(f"{path.relative_to(ROOT)}: {line.strip()}")
    return found


def test_docstrings_hold_at_most_five_benchmark_figures():
    figures = benchmark_figures()
    assert len(figures) <= 5, "\n".join(figures)
