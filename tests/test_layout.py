"""The code's layout, as a newcomer relies on it (issue 24; the README's contributor map): imports point one way,
api -> service -> renderers -> solvers, with no circle at module or function level; nobody imports another
module's `_private` name; no product file over 900 lines; an import inside a function says why it is there
(`# lazy: <reason>`); every product module is reached from what users run; the wheel ships no test configuration.

Read with `ast` from the sources: nothing is imported, so this runs in a second."""
from __future__ import annotations

import ast
import re
from dataclasses import dataclass, field
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
LAYERS = ("api", "service", "renderers", "solvers", "configs")  # each may import only the ones after it
MAX_LINES = 900


@dataclass
class Module:
    name: str  # shadowopt.service.solve
    path: Path
    layer: str
    is_package: bool
    tree: ast.Module = field(repr=False)
    lines: list[str] = field(repr=False)


@dataclass(frozen=True)
class Edge:
    source: str
    target: str
    line: int
    in_function: bool
    names: tuple[str, ...]


def product_modules() -> dict[str, Module]:
    mods = {}
    for layer in LAYERS:
        for path in sorted((REPO / layer).rglob("*.py")):
            rel = path.relative_to(REPO / layer).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            name = ".".join(["shadowopt", layer, *parts])
            text = path.read_text()
            mods[name] = Module(name, path, layer, path.name == "__init__.py", ast.parse(text), text.splitlines())
    return mods


def _absolute(mod: Module, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = mod.name.split(".")
    base = base[: len(base) - node.level + (1 if mod.is_package else 0)]
    return ".".join(base + ([node.module] if node.module else []))


def _enclosing(tree: ast.AST) -> dict[ast.AST, ast.AST]:
    return {child: parent for parent in ast.walk(tree) for child in ast.iter_child_nodes(parent)}


def _inside(node, parents, kinds) -> bool:
    while node in parents:
        node = parents[node]
        if isinstance(node, kinds):
            return True
    return False


def import_edges(mods: dict[str, Module]) -> list[Edge]:
    """Every import of one product module by another, at module level, inside a function or for type checking
    only (a circle through an annotation is still a circle a reader has to follow)."""
    edges = []
    for mod in mods.values():
        parents = _enclosing(mod.tree)
        for node in ast.walk(mod.tree):
            if isinstance(node, ast.Import):
                targets = [(a.name, ()) for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _absolute(mod, node)
                targets = [(f"{base}.{a.name}", ()) if f"{base}.{a.name}" in mods else (base, (a.name,))
                           for a in node.names]
            else:
                continue
            in_function = _inside(node, parents, (ast.FunctionDef, ast.AsyncFunctionDef))
            for target, names in targets:
                if target in mods and target != mod.name:
                    edges.append(Edge(mod.name, target, node.lineno, in_function, names))
    return edges


def function_imports(mods: dict[str, Module]):
    for mod in mods.values():
        parents = _enclosing(mod.tree)
        for node in ast.walk(mod.tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)) and \
                    _inside(node, parents, (ast.FunctionDef, ast.AsyncFunctionDef)):
                yield mod, node


def cycles(nodes, edges: list[Edge]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan's algorithm, iterative)."""
    succ: dict[str, set[str]] = {n: set() for n in nodes}
    for e in edges:
        succ[e.source].add(e.target)
    index, low, stack, on_stack, out, counter = {}, {}, [], set(), [], 0
    for root in nodes:
        if root in index:
            continue
        work = [(root, iter(sorted(succ[root])))]
        index[root] = low[root] = counter; counter += 1
        stack.append(root); on_stack.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter; counter += 1
                    stack.append(w); on_stack.add(w)
                    work.append((w, iter(sorted(succ[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop(); on_stack.discard(w); comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


@pytest.fixture(scope="module")
def mods() -> dict[str, Module]:
    return product_modules()


@pytest.fixture(scope="module")
def edges(mods) -> list[Edge]:
    return import_edges(mods)


def test_the_cycle_finder_finds_a_circle():
    """The checker itself: a -> b -> c -> a is one circle, d -> a is none."""
    es = [Edge("a", "b", 1, False, ()), Edge("b", "c", 1, True, ()), Edge("c", "a", 1, False, ()),
          Edge("d", "a", 1, False, ())]
    assert cycles(["a", "b", "c", "d"], es) == [["a", "b", "c"]]


def test_no_import_circle_at_module_or_function_level(mods, edges):
    found = cycles(list(mods), edges)
    detail = [f"{' <-> '.join(c)}: " + "; ".join(f"{e.source}:{e.line} -> {e.target}" for e in edges
                                                 if e.source in c and e.target in c) for c in found]
    assert not found, "import circles:\n" + "\n".join(detail)


def test_imports_point_one_way(mods, edges):
    """api -> service -> renderers -> solvers; configs imports nothing of ours."""
    wrong = [f"{e.source}:{e.line} imports {e.target}" for e in edges
             if LAYERS.index(mods[e.target].layer) < LAYERS.index(mods[e.source].layer)]
    assert not wrong, "imports against the layers:\n" + "\n".join(wrong)


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def test_no_module_imports_another_modules_private_name(mods, edges):
    wrong = [f"{e.source}:{e.line} imports {e.target}.{n}" for e in edges for n in e.names if _private(n)]
    assert not wrong, "private names imported across modules:\n" + "\n".join(wrong)


def test_no_test_imports_a_private_product_name():
    wrong = []
    for path in sorted((REPO / "tests").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("shadowopt."):
                wrong += [f"{path.relative_to(REPO)}:{node.lineno} {node.module}.{a.name}"
                          for a in node.names if _private(a.name)]
    assert not wrong, "tests importing private product names:\n" + "\n".join(wrong)


def test_no_product_file_over_the_line_cap(mods):
    big = [f"{m.path.relative_to(REPO)}: {len(m.lines)} lines" for m in mods.values() if len(m.lines) > MAX_LINES]
    assert not big, f"files over {MAX_LINES} lines:\n" + "\n".join(big)


LAZY = re.compile(r"#\s*lazy:\s*\S")


def test_an_import_inside_a_function_says_why(mods):
    """Only where needed (an optional dependency, a process that loads its own libLLVM...), with its reason."""
    bare = []
    for mod, node in function_imports(mods):
        said = mod.lines[node.lineno - 1: (node.end_lineno or node.lineno)]
        k = node.lineno - 2  # a reason above a block of imports covers the block
        while k >= 0 and (mod.lines[k].strip().startswith(("#", "import ", "from ")) or not mod.lines[k].strip()):
            said.append(mod.lines[k])
            if mod.lines[k].strip().startswith("#"):
                break
            k -= 1
        if not any(LAZY.search(x) for x in said):
            bare.append(f"{mod.path.relative_to(REPO)}:{node.lineno} {ast.unparse(node)}")
    assert not bare, "imports inside functions without a `# lazy: <reason>`:\n" + "\n".join(bare)


def _started_with_dash_m(mods) -> set[str]:
    """Modules that product code starts as `python -m shadowopt....` (a subprocess, a spawn target)."""
    started = set()
    for mod in mods.values():
        for node in ast.walk(mod.tree):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in mods \
                    and node.value != mod.name:  # a module naming itself (its usage line) starts nothing
                started.add(node.value)
    return started


def test_every_product_module_is_used_by_the_product(mods, edges):
    """Code that only tests use lives under tests/: every module is reached from the CLI, the server, the client
    or a module the product starts in its own process."""
    roots = {"shadowopt.api.cli", "shadowopt.api.server", "shadowopt.api.client"} | _started_with_dash_m(mods)
    succ: dict[str, set[str]] = {}
    for e in edges:
        succ.setdefault(e.source, set()).add(e.target)
    seen, todo = set(roots), list(roots)
    while todo:
        for w in succ.get(todo.pop(), ()):
            if w not in seen:
                seen.add(w); todo.append(w)
    unused = sorted(m for m, mod in mods.items() if m not in seen and not mod.is_package)
    assert not unused, "product modules nothing in the product uses:\n" + "\n".join(unused)


def test_the_wheel_ships_no_test_configuration():
    assert not (REPO / "configs" / "mutation.json").exists(), "the mutation-testing config belongs under tests/"
