"""The plan of the house (``docs/architecture.md``), checked on the source tree: the
layers and their order, no import circle (lazy and type-only imports included), no
module over 600 lines, the loop assembled in one place, and no option's name compared
as a string.

Every import statement anywhere in a module counts, inside functions and under
``if TYPE_CHECKING:`` too: a circle that only a lazy import keeps from failing is still a
circle a reader must untangle.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

LAYERS: tuple[tuple[str, ...], ...] = (
    ("harness.compiled",),
    (
        "harness.grid",
        "harness.velocity",
        "harness.parameters",
        "harness.files",
        "harness.png",
        "harness.fokker_planck",
        "harness.exact_solutions",
        "harness.domains",
    ),
    ("harness.targets",),
    ("harness.records",),
    ("harness.protocols",),
    ("harness.estimators",),
    ("harness.control",),
    ("harness.plants",),
    ("harness.observers",),
    ("harness.loop",),
    ("harness.runs",),
    ("analysis",),
    ("harness.api",),
    ("harness.benchmark",),
    ("experiments",),
)
"""The layers, lowest first, as ``docs/architecture.md`` draws them: a module imports
only from its own layer or a lower one. ``harness.api`` sits above ``analysis``: it
loads logs with :func:`analysis.load.load_run`; ``analysis`` reads only logs.
``harness.benchmark`` composes configs through the API, launches multiruns and reads
their logs back through ``analysis``."""

MAX_LINES = 600
"""Longest module in ``harness/`` and ``analysis/``."""


def modules() -> dict[str, Path]:
    """Every module of ``harness``, ``analysis`` and ``experiments`` by dotted name."""
    out = {}
    for top in ("harness", "analysis", "experiments"):
        for path in sorted((ROOT / top).rglob("*.py")):
            if "conf" in path.relative_to(ROOT).parts:
                continue
            name = ".".join(path.relative_to(ROOT).with_suffix("").parts)
            out[name.removesuffix(".__init__")] = path
    return out


def imports(path: Path, known: dict[str, Path]) -> set[str]:
    """The project's modules ``path`` imports, wherever the statement is."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names: list[str] = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names = [node.module] + [f"{node.module}.{alias.name}" for alias in node.names]
        for name in names:
            # the module itself, or for "from package import module" the module
            if name in known:
                found.add(name)
    return found


def layer(module: str) -> int:
    """The index of ``module``'s layer in :data:`LAYERS`."""
    best = -1, 0
    for index, members in enumerate(LAYERS):
        for prefix in members:
            if module == prefix or module.startswith(prefix + "."):
                best = max(best, (len(prefix), index))
    assert best[0] > 0, f"{module} is in no layer of tests/test_layout.py LAYERS"
    return best[1]


def graph() -> dict[str, set[str]]:
    """Module -> the project's modules it imports (a package's ``__init__`` by its
    package name).
    """
    known = modules()
    return {name: imports(path, known) - {name} for name, path in known.items()}


def test_every_module_lives_in_a_layer_and_imports_no_higher_one():
    wrong = []
    for module, deps in graph().items():
        for dep in deps:
            if layer(dep) > layer(module):
                wrong.append(f"{module} (layer {layer(module)}) imports {dep} ({layer(dep)})")
    assert not wrong, "\n".join(sorted(wrong))


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def test_cycles_finds_a_circle_and_a_self_contained_tree():
    """The detector itself, on graphs whose answer is known."""
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []


def test_no_import_circle():
    assert cycles(graph()) == []


def test_no_package_init_imports_the_project():
    """A package's ``__init__`` imports nothing of the project (most hold only their
    docstring), so importing one module of a package never imports its siblings."""
    known = modules()
    for path in (ROOT / "harness").rglob("__init__.py"):
        assert imports(path, known) == set(), path


@pytest.mark.parametrize("top", ["harness", "analysis"])
def test_no_module_over_600_lines(top):
    long = {
        str(path.relative_to(ROOT)): n
        for path in (ROOT / top).rglob("*.py")
        if (n := len(path.read_text().splitlines())) > MAX_LINES
    }
    assert not long, long


def test_the_loop_is_assembled_in_one_place():
    """``ClosedLoop(...)`` is called only by :func:`harness.loop.trajectory`."""
    calls = []
    for top in ("harness", "analysis", "experiments", "benchmarks", "tests", "examples"):
        for path in (ROOT / top).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Call) and getattr(node.func, "id", "") == "ClosedLoop":
                    calls.append(f"{path.relative_to(ROOT)}:{node.lineno}")
    assert calls == [f"harness/loop.py:{_trajectory_line()}"], calls


def _trajectory_line() -> int:
    """The line of the ``ClosedLoop(...)`` call inside :func:`harness.loop.trajectory`."""
    tree = ast.parse((ROOT / "harness" / "loop.py").read_text())
    (func,) = [n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == "trajectory"]
    (call,) = [
        n
        for n in ast.walk(func)
        if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "ClosedLoop"
    ]
    return call.lineno


def option_names() -> set[str]:
    """The option names of the config groups a component is chosen from, and the values
    of every config key whose comment lists its choices (``consensus: first_order  #
    first_order | pi: ...`` gives ``first_order`` and ``pi``).
    """
    groups = ("plant", "estimator", "control", "target", "init", "observers", "filter", "design")
    names = {p.stem for g in groups for p in (ROOT / "conf" / g).glob("*.yaml")}
    for path in (ROOT / "conf").rglob("*.yaml"):
        for line in path.read_text().splitlines():
            setting, _, comment = line.partition("#")
            if ":" in setting and "|" in comment:
                for choice in comment.split("|"):
                    match = re.match(r"\s*([a-z_][a-z0-9_]*)\b", choice)
                    if match:
                        names.add(match.group(1))
    return names


def compared_strings(tree: ast.AST) -> list[tuple[int, str]]:
    """String constants compared with ``==``, ``!=``, ``in`` or ``not in`` (alone or in a
    literal tuple, list or set), with their lines."""
    out = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Compare):
            continue
        for operand in [node.left, *node.comparators]:
            literal = isinstance(operand, (ast.Tuple, ast.List, ast.Set))
            items = operand.elts if literal else [operand]
            for item in items:
                if isinstance(item, ast.Constant) and isinstance(item.value, str):
                    out.append((node.lineno, item.value))
    return out


def test_compared_strings_sees_comparisons():
    tree = ast.parse('a == "pi"\nb in ("grid", "band")\nc = {"pi": 1}\n')
    assert compared_strings(tree) == [(1, "pi"), (2, "grid"), (2, "band")]


def test_no_option_name_is_compared_as_a_string():
    """An option is a class chosen once from the config, never a name compared later."""
    names = option_names()
    found = []
    for top in ("harness", "analysis"):
        for path in (ROOT / top).rglob("*.py"):
            for line, value in compared_strings(ast.parse(path.read_text())):
                if value in names:
                    found.append(f"{path.relative_to(ROOT)}:{line}: {value!r}")
    assert not found, "\n".join(found)
