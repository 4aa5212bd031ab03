"""The package's shape stays what DESIGN.md promises: no import cycle among its modules, no
private name imported from another module, no module over 800 lines, and no solver or batch
code that knows a concrete control family."""

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1] / "jaxtraj"
FAMILIES = {"PiecewiseLinear", "PiecewiseParabolic", "PiecewiseConstant", "SaturatedSpline"}


def _modules():
    mods = {}
    for path in ROOT.rglob("*.py"):
        parts = path.relative_to(ROOT.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        mods[name] = path
    return mods


def _imports(name, path, mods):
    """`(module, imported name, line)` of every `from jaxtraj... import x` in one module."""
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            elif (node.module or "").startswith("jaxtraj"):
                target = node.module
            else:
                continue
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                yield (sub, None, node.lineno) if sub in mods else (target, alias.name, node.lineno)


MODS = _modules()
EDGES = {
    name: {t for t, _, _ in _imports(name, path, MODS) if t in MODS and MODS[t].name != "__init__.py"}
    for name, path in MODS.items()
    if path.name != "__init__.py"
}


def test_no_import_cycle():
    state = {}

    def visit(m, stack):
        state[m] = "open"
        for t in sorted(EDGES.get(m, ())):
            if state.get(t) == "open":
                pytest.fail("import cycle: " + " -> ".join([*stack[stack.index(t) :], t]))
            if t not in state:
                visit(t, [*stack, t])
        state[m] = "done"

    for m in sorted(EDGES):
        if m not in state:
            visit(m, [m])


def test_no_private_name_imported_across_modules():
    bad = [
        f"{path}:{line}: {imported} from {target}"
        for name, path in MODS.items()
        for target, imported, line in _imports(name, path, MODS)
        if imported and imported.startswith("_") and target != name
    ]
    assert not bad, bad


def test_modules_stay_under_800_lines():
    big = {str(p): n for p in MODS.values() if (n := len(p.read_text().splitlines())) > 800}
    assert not big, big


def test_only_the_families_module_names_concrete_families():
    """Solvers, batching and problems use what a family declares (its layout), never which
    family it is (`isinstance` on a concrete class)."""
    bad = []
    for path in MODS.values():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "isinstance":
                names = {n.id for n in ast.walk(node.args[1]) if isinstance(n, ast.Name)}
                if names & FAMILIES:
                    bad.append(f"{path}:{node.lineno}")
    assert not bad, bad
