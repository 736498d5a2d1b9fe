"""Process state kept at module level: none in the numerics, and every cache or registry elsewhere is listed,
with its measurement, in docs/design.md ("Module-level caches")."""
import ast

from conftest import REPO

CACHING = {"cache", "lru_cache"}
EMPTY = {"dict", "set", "list", "OrderedDict", "defaultdict", "deque"}


def module_state(path) -> list[str]:
    """Names of a module's functools caches on module-level functions and of the empty containers its
    module level creates (what it fills while it runs)."""
    found = []
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.FunctionDef):
            for d in node.decorator_list:
                target = d.func if isinstance(d, ast.Call) else d
                if (target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", None)) in CACHING:
                    found.append(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)) and node.value is not None:
            value = node.value
            empty = isinstance(value, (ast.Dict, ast.Set, ast.List)) and not (
                getattr(value, "keys", None) or getattr(value, "elts", None))
            if isinstance(value, ast.Call) and not value.args and not value.keywords:
                func = value.func
                empty = (func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", None)) in EMPTY
            if empty:
                targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                found += [t.id for t in targets if isinstance(t, ast.Name)]
    return found


def test_the_numerics_keep_no_state_between_calls():
    state = {f"{p.relative_to(REPO)}: {name}" for p in (REPO / "rdsexp" / "numerics").rglob("*.py")
             for name in module_state(p)}
    assert not state, sorted(state)


def test_every_module_level_cache_is_listed_with_its_measurement():
    text = (REPO / "docs" / "design.md").read_text()
    section = text.split("## Module-level caches", 1)[1].split("\n## ", 1)[0]
    state = [(p, name) for p in (REPO / "rdsexp").rglob("*.py") for name in module_state(p)]
    assert state                                          # the scan finds what is there
    module = lambda p: p.parent.name if p.stem == "__init__" else p.stem
    missing = [f"{p.relative_to(REPO)}: {name}" for p, name in state if f"{module(p)}.{name}`" not in section]
    assert not missing, f"not in docs/design.md's Module-level caches: {missing}"
