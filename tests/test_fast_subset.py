"""The fast subset, `python -m pytest -m "not slow"` (docs/development.md), exercises every module of rdsexp/.

A test not marked slow names a module when its body, its parametrize arguments, or the helpers, fixtures
and module-level values of its file and of conftest.py that it reaches read a name that resolves to the
module or to something defined in it (`rx.paper.plant`: rdsexp/__init__.py and paper; `from
rdsexp.experiment.store import Run`: store/__init__.py and store/run.py), or run it as `python -m MODULE`;
the conftest helper `rdsexp(...)` names cli and the catalog (its in-process main()). A module is exercised
when a fast test names it; names a module that imports a name from it (one step: a run's cli writes
through store/writer.py); or names a package whose __init__.py imports it, directly or through the
package's other modules (`rx.synthesize(..., "proposed")` runs synthesis/lmi.py and its bisection.py).
Read from the source, not from a run, so the answer does not depend on which worker ran what."""
import ast
import importlib
import inspect
import types
from functools import cache
from pathlib import Path

import pytest
from conftest import REPO, import_source
from test_package import MODULES, PACKAGE

TESTS = REPO / "tests"
HELPERS = {p.stem: p for p in TESTS.glob("*.py")}          # importable from every test file (pythonpath = tests)


def is_slow(decorator: ast.expr) -> bool:
    """`@pytest.mark.slow` or `@pytest.mark.slow(...)`."""
    node = decorator.func if isinstance(decorator, ast.Call) else decorator
    return ast.unparse(node) == "pytest.mark.slow"


def marks_module_slow(tree: ast.Module) -> bool:
    """`pytestmark = pytest.mark.slow` (or a list holding it) at the top of a file."""
    for node in tree.body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "pytestmark" for t in node.targets):
            values = node.value.elts if isinstance(node.value, (ast.List, ast.Tuple)) else [node.value]
            return any(is_slow(v) for v in values)
    return False


def imports(nodes) -> dict:
    """{local name: (module, attribute or None)} of the import statements among `nodes` (at any depth)."""
    found = {}
    for node in (n for top in nodes for n in ast.walk(top)):
        if isinstance(node, ast.Import):
            for alias in node.names:
                # `import a.b as c`: c is a.b; `import a.b`: the name a, the package a
                found[alias.asname or alias.name.split(".")[0]] = (alias.name if alias.asname else
                                                                   alias.name.split(".")[0], None)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            for alias in node.names:
                found[alias.asname or alias.name] = (node.module, alias.name)
    return found


@cache
def parsed(path: Path):
    """(tree, {name: top-level def, class or assignment}, {name: import}) of a test file or conftest.py."""
    tree = ast.parse(path.read_text())
    defs = {}
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            defs[node.name] = node
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            for target in node.targets if isinstance(node, ast.Assign) else [node.target]:
                for name in ast.walk(target):
                    if isinstance(name, ast.Name):
                        defs[name.id] = node
    return tree, defs, imports([n for n in tree.body if not isinstance(n, (ast.FunctionDef, ast.ClassDef))])


def fixture_of(node) -> bool:
    return isinstance(node, ast.FunctionDef) and any("fixture" in ast.unparse(d) for d in node.decorator_list)


def autouse(node) -> bool:
    return fixture_of(node) and any("autouse=True" in ast.unparse(d) for d in node.decorator_list)


def chains(node):
    """Every `name.attr.attr` read in `node` as (name, [attr, ...]), the longest chain of each."""
    inner = set()
    for sub in ast.walk(node):
        if isinstance(sub, ast.Attribute):
            inner.add(id(sub.value))
    for sub in ast.walk(node):
        if isinstance(sub, (ast.Attribute, ast.Name)) and id(sub) not in inner:
            attrs = []
            while isinstance(sub, ast.Attribute):
                attrs.insert(0, sub.attr)
                sub = sub.value
            if isinstance(sub, ast.Name):
                yield sub.id, attrs


def python_m(node) -> set[str]:
    """Modules of rdsexp a list or tuple literal runs as `python -m MODULE` (a package: its __main__)."""
    found = set()
    for sub in ast.walk(node):
        if isinstance(sub, (ast.List, ast.Tuple)):
            items = [e.value if isinstance(e, ast.Constant) else None for e in sub.elts]
            for flag, name in zip(items, items[1:]):
                if flag == "-m" and name in MODULES:
                    main = f"{name}.__main__"
                    found.add(main if main in MODULES else name)
    return found


def resolve(source: tuple, attrs: list[str]) -> set[str]:
    """The modules of rdsexp a name imported as `source` and read as name.attrs names: every module along
    the chain and the module that defines what it ends at."""
    module, attribute = source
    if not (module == "rdsexp" or module.startswith("rdsexp.")):
        return set()
    path = [attribute, *attrs] if attribute else attrs
    obj, found = importlib.import_module(module), {module}
    for name in path:
        sub = f"{obj.__name__}.{name}" if isinstance(obj, types.ModuleType) else None
        if sub in MODULES:
            obj = importlib.import_module(sub)
        elif hasattr(obj, name):
            obj = getattr(obj, name)
        else:
            break
        if isinstance(obj, types.ModuleType):
            found.add(obj.__name__)
    defined = getattr(obj if inspect.isclass(obj) or callable(obj) else type(obj), "__module__", None)
    found.add(defined)
    return {m for m in found if m in MODULES}


@cache
def imported_from(module: str) -> frozenset[str]:
    """The modules of rdsexp that define what `module` imports (at any depth, relative imports resolved):
    `from .store import RunStore` in runner.py is store/runstore.py."""
    path = MODULES[module]
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            source = import_source(node, package)
            for alias in node.names:
                if alias.name != "*":
                    found |= resolve((source, alias.name), [])
        elif isinstance(node, ast.Import):
            found |= {alias.name for alias in node.names}
    return frozenset(found & set(MODULES) - {module})


@cache
def facade(package: str) -> frozenset[str]:
    """The modules of `package` that its __init__.py imports, directly or through one another (what a call
    through the package reaches: `rx.synthesize(..., "proposed")` runs synthesis/lmi.py and its bisection.py)."""
    found, todo = set(), [package]
    while todo:
        for module in imported_from(todo.pop()) - found:
            if module.startswith(f"{package}."):
                found.add(module)
                todo.append(module)
    return frozenset(found)


def reached(path: Path, test: ast.FunctionDef) -> set[str]:
    """The modules of rdsexp the test `test` of the file `path` names, through what it reaches."""
    todo = [(path, test)]
    tree, defs, _ = parsed(path)
    todo += [(path, node) for node in defs.values() if autouse(node)]
    seen, modules = set(), set()
    while todo:
        where, node = todo.pop()
        if (where, id(node)) in seen:
            continue
        seen.add((where, id(node)))
        _, defs, names = parsed(where)
        inside = imports([node])
        local = names | inside
        requested = {a.arg for a in node.args.args} if isinstance(node, ast.FunctionDef) else set()
        # a variable of the function (`lmi = rx.synthesize(...)`) is not the module or helper of that name
        bound = {n.id for n in ast.walk(node) if isinstance(n, ast.Name) and isinstance(n.ctx, ast.Store)} | {
            a.arg for a in ast.walk(node) if isinstance(a, ast.arg)} - requested - set(inside)
        modules |= python_m(node)
        for name, attrs in [*chains(node), *((r, []) for r in requested)]:
            if name in bound and not isinstance(node, (ast.Assign, ast.AnnAssign)):
                continue
            if name in defs and defs[name] is not node:
                todo.append((where, defs[name]))
            elif name in local and local[name][0] in HELPERS:          # from conftest import SMALL, rdsexp
                other = HELPERS[local[name][0]]
                target = parsed(other)[1].get(local[name][1] or "")
                if target is not None:
                    todo.append((other, target))
            elif name in local:
                modules |= resolve(local[name], attrs)
            elif name in parsed(HELPERS["conftest"])[1]:                # a conftest fixture requested by name
                todo.append((HELPERS["conftest"], parsed(HELPERS["conftest"])[1][name]))
    return modules


def fast_tests():
    """(path, test function) of every test not marked slow."""
    for path in sorted(TESTS.rglob("test_*.py")):
        tree, _, _ = parsed(path)
        if marks_module_slow(tree):
            continue
        for node in tree.body:
            if isinstance(node, ast.FunctionDef) and node.name.startswith("test_"):
                if not any(is_slow(d) for d in node.decorator_list):
                    yield path, node


@cache
def exercised() -> dict[str, list[str]]:
    """{module: the fast tests that exercise it}."""
    found = {}
    for path, test in fast_tests():
        named = reached(path, test)
        packages = [m for m in named if MODULES[m].name == "__init__.py"]
        for module in named.union(*(imported_from(m) for m in named), *(facade(p) for p in packages)):
            found.setdefault(module, []).append(f"{path.relative_to(REPO)}::{test.name}")
    return found


@pytest.mark.parametrize("module", sorted(MODULES), ids=lambda m: str(MODULES[m].relative_to(PACKAGE)))
def test_every_module_is_exercised_by_a_fast_test(module):
    assert module in exercised(), f"{module}: no test outside the slow ones names it (mark fewer slow, or add one)"


def test_the_check_tells_slow_tests_from_fast_ones():
    """Tests marked slow do not count: the docs' examples (every one of them slow) are no fast test, and
    a helper reached only from slow tests adds nothing (test_sweep's `basic` launcher sweep)."""
    fast = {(p.name, t.name) for p, t in fast_tests()}
    assert ("test_docs.py", "test_examples_run") not in fast
    assert ("test_package.py", "test_no_import_cycles") in fast
    assert not any(name.startswith("tests/test_docs_guides") for tests in exercised().values() for name in tests)
    sweep = TESTS / "experiment" / "test_sweep.py"
    tests = {t.name: t for t in ast.parse(sweep.read_text()).body if isinstance(t, ast.FunctionDef)}
    assert "rdsexp.experiment.cli" in reached(sweep, tests["test_joblib_workers_give_the_basic_tables_and_a_complete_summary"])
