"""The import rules of DESIGN.md ("Allowed imports"), held on the source with ``ast``.

Every import counts, a function-level one as much as a module-level one: it closes the same circle
when it runs. Over harness/, models/, simulator/ and benchmarks/:
- models and simulator import harness only through the floor, harness.core;
- harness.core imports nothing of the project outside harness.core;
- no import circle between modules;
- nothing imports harness.cli (its one caller is the console entry point in pyproject.toml);
- no module uses another module's private (underscore) name.
"""
from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("harness", "models", "simulator", "benchmarks")
FLOOR = "harness.core"
CLI = "harness.cli"


@dataclass(frozen=True)
class Use:
    """``source`` (line ``line``) imports the module ``target``, or its name ``name``."""

    source: str
    target: str
    line: int
    name: str | None = None
    attribute: bool = False  # a use of ``name`` through a module bound earlier, not an import

    def __str__(self) -> str:
        return f"{self.source} (line {self.line}) -> {self.target}{'.' + self.name if self.name else ''}"


def find_modules(root: Path, packages=PACKAGES) -> dict[str, Path]:
    """Dotted module name -> file, for every .py file under the packages."""
    found = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def _is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _owner(dotted: str, modules) -> str | None:
    """The longest prefix of ``dotted`` that is a project module."""
    parts = dotted.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in modules:
            return ".".join(parts[:n])
    return None


def _base(module: str, node: ast.ImportFrom, is_package: bool) -> str:
    if not node.level:
        return node.module or ""
    parts = module.split(".")
    up = parts if is_package else parts[:-1]
    up = up[: len(up) - node.level + 1]
    return ".".join(up + ([node.module] if node.module else []))


def _imports(module: str, tree: ast.AST, modules, is_package: bool):
    """Every import in ``tree`` as Uses, and the local names bound to project modules."""
    uses, bound = [], {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                target = _owner(alias.name, modules)
                if target:
                    uses.append(Use(module, target, node.lineno))
                    if alias.asname:
                        bound[alias.asname] = target
                    else:  # ``import a.b`` binds ``a``, reached as ``a.b.name``
                        bound[alias.name.split(".")[0]] = alias.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom):
            base = _base(module, node, is_package)
            for alias in node.names:
                sub = f"{base}.{alias.name}"
                if sub in modules:
                    uses.append(Use(module, sub, node.lineno))
                    bound[alias.asname or alias.name] = sub
                elif base in modules:
                    uses.append(Use(module, base, node.lineno, alias.name))
    return uses, bound


def _dotted(node: ast.AST) -> str | None:
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        head = _dotted(node.value)
        return None if head is None else f"{head}.{node.attr}"
    return None


def _attribute_uses(module: str, tree: ast.AST, bound: dict, modules) -> list[Use]:
    """``infer._frame_inputs`` after ``from harness import infer``: a use of a module's name."""
    uses = []
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute):
            continue
        dotted = _dotted(node.value)
        if dotted is None or dotted.split(".")[0] not in bound:
            continue
        head, _, rest = dotted.partition(".")
        target = bound[head] + (f".{rest}" if rest else "")
        if target in modules:
            uses.append(Use(module, target, node.lineno, node.attr, attribute=True))
    return uses


def collect_uses(root: Path, packages=PACKAGES) -> tuple[dict[str, Path], list[Use]]:
    modules = find_modules(root, packages)
    uses = []
    for module, path in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
        found, bound = _imports(module, tree, modules, path.name == "__init__.py")
        uses += found + _attribute_uses(module, tree, bound, modules)
    return modules, uses


def _in(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def layer_breaches(uses) -> list[str]:
    out = []
    for use in uses:
        if use.source == use.target:
            continue
        if use.name and _is_private(use.name):
            out.append(f"{use}: a private name of another module; make it public or keep it inside")
        if use.attribute:
            continue
        if _in(use.source, "models") or _in(use.source, "simulator"):
            if _in(use.target, "harness") and not _in(use.target, FLOOR):
                out.append(f"{use}: models and simulator import harness only through {FLOOR}")
        if _in(use.source, FLOOR) and not _in(use.target, FLOOR):
            out.append(f"{use}: {FLOOR} imports nothing of the project above it")
        if use.target == CLI:
            out.append(f"{use}: nothing imports {CLI} (only the console entry point calls it)")
    return sorted(set(out))


def circles(uses) -> list[list[str]]:
    """One circle (``[a, b, ..., a]``) per strongly connected group of modules."""
    graph: dict[str, set[str]] = {}
    for use in uses:
        if use.source != use.target:
            graph.setdefault(use.source, set()).add(use.target)
    index, low, stack, on_stack, groups = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            group = set()
            while True:
                w = stack.pop()
                on_stack.discard(w)
                group.add(w)
                if w == v:
                    break
            if len(group) > 1:
                groups.append(group)

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return [_circle_in(graph, group) for group in groups]


def _circle_in(graph, group: set[str]) -> list[str]:
    """A shortest circle through the group's first module, by breadth-first search."""
    start = min(group)
    paths = {start: [start]}
    queue = [start]
    while queue:
        v = queue.pop(0)
        for w in sorted(graph.get(v, ()) & group):
            if w == start:
                return paths[v] + [start]
            if w not in paths:
                paths[w] = paths[v] + [w]
                queue.append(w)
    raise AssertionError(f"no circle found in {sorted(group)}")


def _report(problems: list[str]) -> str:
    return "\n".join(f"  {p}" for p in problems)


def test_layers_and_seams():
    _, uses = collect_uses(ROOT)
    problems = layer_breaches(uses)
    assert not problems, "import rules broken:\n" + _report(problems)


def test_no_import_circles():
    _, uses = collect_uses(ROOT)
    found = [" -> ".join(circle) for circle in circles(uses)]
    assert not found, "import circles (function-level imports included):\n" + _report(found)


def test_each_rule_names_what_breaks_it(tmp_path):
    """The checks themselves, on a made-up tree that breaks every rule once."""
    files = {
        "harness/__init__.py": "",
        "harness/core/__init__.py": "",
        "harness/core/files.py": "def f():\n    from harness import notes\n",
        "harness/run.py": "from harness.core import files\n\ndef g():\n    from harness.report import h\n",
        "harness/report.py": "from harness import tables\n\ndef h():\n    return tables._hidden\n",
        "harness/tables.py": "import harness.run\n",
        "harness/cli.py": "",
        "harness/notes.py": "from harness.cli import main\n",
        "models/__init__.py": "",
        "models/m.py": "from harness.core.files import f\nfrom harness.run import g\n",
        "simulator/s.py": "from harness import report\n",
        "benchmarks/b.py": "from harness.core import files\nfiles._private()\n",
    }
    for rel, text in files.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text)
    _, uses = collect_uses(tmp_path)
    problems = layer_breaches(uses)
    expected = ["models.m (line 2) -> harness.run.g: models and simulator import harness only through harness.core",
                "simulator.s (line 1) -> harness.report: models and simulator import harness only through harness.core",
                "harness.core.files (line 2) -> harness.notes: harness.core imports nothing of the project above it",
                "harness.notes (line 1) -> harness.cli.main: nothing imports harness.cli (only the console entry point "
                "calls it)",
                "harness.report (line 4) -> harness.tables._hidden: a private name of another module; make it public "
                "or keep it inside",
                "benchmarks.b (line 2) -> harness.core.files._private: a private name of another module; make it "
                "public or keep it inside"]
    assert sorted(problems) == sorted(expected)
    assert circles(uses) == [["harness.report", "harness.tables", "harness.run", "harness.report"]]
