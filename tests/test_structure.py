"""The code's shape, enforced: the benchmarks stay out of the product, the robot's sensing record
is declared once, and every module and function stays small enough to read."""

from __future__ import annotations

import ast
import io
import tokenize
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SOURCES = [p for d in ("client", "protocol", "service", "sim_backend", "examples") for p in (ROOT / d).rglob("*.py")]


def _imports(path: Path) -> set[str]:
    """The modules ``path`` imports, named from the source tree's top (``service.bench``, not
    ``inhand_tracker.service.bench``): relative imports resolve against its folders."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the module's package
                package = path.relative_to(ROOT).parent.parts[
                    : len(path.relative_to(ROOT).parent.parts) - node.level + 1
                ]
                out.add(".".join([*package, node.module or ""]).rstrip("."))
            else:
                out.add(node.module or "")
    return {m.removeprefix("inhand_tracker.") for m in out}


def test_nothing_outside_the_benchmarks_imports_them():
    bench = ROOT / "service" / "bench"
    # The command line is the one door into every part, the benchmarks' included.
    allowed = {bench, ROOT / "service" / "cli"}
    offenders = {
        str(p.relative_to(ROOT)): sorted(m for m in _imports(p) if m.startswith("service.bench"))
        for p in SOURCES
        if not any(p == a or a in p.parents for a in allowed)
    }
    assert not {k: v for k, v in offenders.items() if v}


def _names_sensing(path: Path) -> bool:
    """Whether ``path``'s code (not its prose) names a field only sensing has: an identifier
    slip, slip_dir, spin or spin_sense, or the string of one ("slip" alone is also an ablation's
    name, so strings count only for the unambiguous two)."""
    for token in tokenize.generate_tokens(io.StringIO(path.read_text()).readline):
        if token.type == tokenize.NAME and token.string in ("slip", "slip_dir", "spin", "spin_sense"):
            return True
        if token.type == tokenize.STRING and token.string.strip("\"'") in ("slip_dir", "spin_sense"):
            return True
    return False


def test_the_sensing_record_is_named_in_at_most_three_source_files():
    naming = sorted(str(p.relative_to(ROOT)) for p in SOURCES if _names_sensing(p))
    # Where it is declared, where the simulator senses it, and where the cost compares it.
    assert naming == ["protocol/sensing.py", "service/tracker/cost.py", "sim_backend/observe.py"], naming


def test_modules_and_functions_stay_small():
    """A module over 450 lines holds more than one concern; a function over 80 lines, more than one step."""
    long_files = {str(p.relative_to(ROOT)): n for p in SOURCES if (n := len(p.read_text().splitlines())) > 450}
    assert not long_files, long_files
    long_functions = {
        f"{p.relative_to(ROOT)}:{node.name}": node.end_lineno - node.lineno + 1
        for p in SOURCES
        for node in ast.walk(ast.parse(p.read_text()))
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.end_lineno - node.lineno + 1 > 80
    }
    assert not long_functions, long_functions


def _module(path: Path) -> str:
    """``path``'s module name from the source tree's top (``service.server.pools``; a package by its folder)."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _project_imports(path: Path, modules: set[str]) -> set[str]:
    """The project's modules ``path`` imports, anywhere in it (a function's import and a type
    checker's count too): ``from . import x`` is x where x is a module, else the package."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names = [a.name.removeprefix("inhand_tracker.") for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                package = _module(path).split(".")[: None if path.name == "__init__.py" else -1]
                base = ".".join(package[: len(package) - node.level + 1] + ([node.module] if node.module else []))
            else:
                base = (node.module or "").removeprefix("inhand_tracker.")
            names = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
        else:
            continue
        for name in names:
            while name and name not in modules:  # a name inside a module: the module
                name = name.rpartition(".")[0]
            if name and name != _module(path):
                out.add(name)
    return out


def test_no_module_imports_one_that_imports_it_back():
    """No import circles, type-only ones included: a function carved out of a class that takes the
    whole object back is a circle; the record it needs goes to a module of its own."""
    files = [p for p in SOURCES if "examples" not in p.parts]
    modules = {_module(p) for p in files}
    graph = {_module(p): _project_imports(p, modules) for p in files}

    def reaches(start: str, goal: str) -> bool:
        seen, todo = set(), [start]
        while todo:
            m = todo.pop()
            if m == goal:
                return True
            if m not in seen:
                seen.add(m)
                todo += graph.get(m, ())
        return False

    circles = sorted(f"{a} -> {b}" for a, out in graph.items() for b in out if reaches(b, a))
    assert not circles, circles


def test_the_client_imports_neither_the_service_nor_the_simulation():
    """The robot side is protocol and zenoh: not even a function of it reaches into the GPU side."""
    reaching = {
        str(p.relative_to(ROOT)): sorted(m for m in _imports(p) if m.startswith(("service", "sim_backend")))
        for p in (ROOT / "client").rglob("*.py")
    }
    assert not {k: v for k, v in reaching.items() if v}, reaching
