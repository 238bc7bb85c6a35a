"""The package's layers import only downward (README "Layout"), with no import cycle.

Read from the source with ``ast`` (nothing is imported): every ``import hairexp...`` and
``from hairexp... import`` of every module under hairexp/, at module level or inside a function.

    errors < model < guides < physics < control < io, outputs, evaluation < app

``io``, ``outputs`` and ``evaluation`` are peers: none imports another.  Nothing imports the app
layer (entry points such as ``python -m hairexp`` and ``python -m hairexp.io.export_scene`` are
app modules that nothing imports).  Physics never names a controller.  A function-local import of
a hairexp module is allowed only for the modules that load a heavy optional library (pxr,
rerun), so that a scene without USD or logging never loads it.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "hairexp"

#: layer of each top-level part of the package (a subpackage or a module directly under hairexp/)
LAYERS = {
    "__init__": 0, "errors": 0, "memory": 0,
    "model": 1,
    "guides": 2,
    "physics": 3,
    "control": 4,
    "io": 5, "outputs": 5, "evaluation": 5,
    "app": 6, "__main__": 6,
}
#: entry-point modules outside app/ that belong to the app layer (run with python -m, never imported)
ENTRY_POINTS = {"hairexp.io.export_scene": 6}
#: modules that may be imported inside a function (they import pxr or rerun at module level)
LAZY = {"hairexp.io.usd_read", "hairexp.io.usd_write", "hairexp.outputs.rerun_sink", "hairexp.outputs.comparison"}


def module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted(PKG.rglob("*.py"))}


def layer_of(mod: str) -> int:
    if mod in ENTRY_POINTS:
        return ENTRY_POINTS[mod]
    parts = mod.split(".")
    return LAYERS[parts[1] if len(parts) > 1 else "__init__"]


def part_of(mod: str) -> str:
    parts = mod.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def resolve(target: str, known: dict[str, Path]) -> str:
    """The hairexp module an import names (``from hairexp.a import b``: module a.b if it exists)."""
    while target not in known and "." in target:
        target = target.rsplit(".", 1)[0]
    return target


def imports(mod: str, path: Path, known: dict[str, Path]) -> list[tuple[str, int, bool]]:
    """(imported hairexp module, line, inside a function) of one module."""
    tree = ast.parse(path.read_text(), str(path))
    out = []

    def visit(node, in_function: bool):
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            if isinstance(child, ast.Import):
                for a in child.names:
                    if a.name == "hairexp" or a.name.startswith("hairexp."):
                        out.append((resolve(a.name, known), child.lineno, in_function))
            elif isinstance(child, ast.ImportFrom):
                if child.level:   # relative: resolve against this module's package
                    base = mod if path.name == "__init__.py" else mod.rsplit(".", 1)[0]
                    for _ in range(child.level - 1):
                        base = base.rsplit(".", 1)[0]
                    name = f"{base}.{child.module}" if child.module else base
                else:
                    name = child.module or ""
                if name == "hairexp" or name.startswith("hairexp."):
                    for a in child.names:
                        out.append((resolve(f"{name}.{a.name}", known), child.lineno, in_function))
            visit(child, inner)

    visit(tree, False)
    return [(t, line, f) for t, line, f in out if t != mod]


def graph() -> dict[str, list[tuple[str, int, bool]]]:
    known = modules()
    return {m: imports(m, p, known) for m, p in known.items()}


def test_every_module_has_a_layer():
    for m in modules():
        layer_of(m)   # KeyError names a part of the package missing from LAYERS


def test_layers_import_only_downward():
    bad = []
    for m, deps in graph().items():
        for t, line, _ in deps:
            lm, lt = layer_of(m), layer_of(t)
            peers = lm == lt == 5 and part_of(m) != part_of(t) and m not in ENTRY_POINTS
            if lt > lm or peers:
                bad.append(f"{m}:{line} imports {t} (layer {lm} -> {lt})")
    assert not bad, "imports that run up or sideways:\n" + "\n".join(bad)


def test_nothing_imports_the_app_layer():
    bad = [f"{m}:{line} imports {t}" for m, deps in graph().items() for t, line, _ in deps
           if layer_of(t) == 6 and layer_of(m) < 6]
    assert not bad, "\n".join(bad)


def test_there_is_no_import_cycle():
    g = {m: sorted({t for t, _, _ in deps}) for m, deps in graph().items()}
    WHITE, GREY, BLACK = 0, 1, 2
    color = dict.fromkeys(g, WHITE)
    cycles = []

    def dfs(u, stack):
        color[u] = GREY
        stack.append(u)
        for v in g.get(u, []):
            if color.get(v, BLACK) == GREY:
                cycles.append(stack[stack.index(v):] + [v])
            elif color.get(v) == WHITE:
                dfs(v, stack)
        stack.pop()
        color[u] = BLACK

    for m in g:
        if color[m] == WHITE:
            dfs(m, [])
    # a package's __init__ importing its own submodule is not a cycle by itself; report the rest
    real = [c for c in cycles if not all(a.startswith(c[0]) or c[0].startswith(a) for a in c)]
    assert not real, "import cycles:\n" + "\n".join(" -> ".join(c) for c in real)


def test_function_local_imports_are_only_for_heavy_optional_libraries():
    bad = [f"{m}:{line} imports {t} inside a function" for m, deps in graph().items() for t, line, local in deps
           if local and t not in LAZY]
    assert not bad, "\n".join(bad)


def test_physics_never_names_a_controller():
    bad = []
    for p in sorted((PKG / "physics").rglob("*.py")):
        text = p.read_text()
        for word in ("hairexp.control", "TrackingController", "AttractController", "SkinnedController", "GuideSkinning"):
            if word in text:
                bad.append(f"{p.name}: {word}")
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("case", ["upward", "cycle"])
def test_the_checks_catch_what_they_are_for(case, tmp_path, monkeypatch):
    """The same checks over a tiny package with the fault built in: they must fail."""
    pkg = tmp_path / "hairexp"
    (pkg / "model").mkdir(parents=True)
    (pkg / "physics").mkdir()
    for d in (pkg, pkg / "model", pkg / "physics"):
        (d / "__init__.py").write_text("")
    (pkg / "errors.py").write_text("")
    (pkg / "physics" / "step.py").write_text("from hairexp.model.scene import Scene\n")
    if case == "upward":
        (pkg / "model" / "scene.py").write_text("def f():\n    from hairexp.physics.step import g\n")
        check = test_layers_import_only_downward
    else:
        (pkg / "model" / "scene.py").write_text("from hairexp.model.other import x\n")
        (pkg / "model" / "other.py").write_text("from hairexp.model.scene import Scene\n")
        check = test_there_is_no_import_cycle
    monkeypatch.setattr(__import__(__name__), "PKG", pkg)
    with pytest.raises(AssertionError):
        check()
