"""The import direction of the package, enforced on the source (an AST scan of every module).

Layers, lowest first: ``objectives`` (the loss, a leaf) <- the core (``tar_rl`` itself: data
format, policies, runs, metrics, reports, importers) <- ``collectors`` (simulator suites) <-
``recipes`` <- the command line (``tar_rl.cli``, ``tar_rl.__main__``); the benchmark scripts sit on
top. A module may import its own layer and the layers below it, never above, wherever the import
statement is (module level or inside a function). The registry class lives in the leaf
(``tar_rl.objectives.registry``), so that ``objectives`` imports nothing from the rest of the package;
the package's ``__init__`` re-exports objectives lazily.
No module imports another module's private name (``from m import _x`` or ``m._x``).
"""

from __future__ import annotations

import ast
from pathlib import Path

from paths import REPO

ROOT = REPO
# folder -> (import package, layer)
FOLDERS = {
    "objectives": ("tar_rl.objectives", 0),
    "tar_rl": ("tar_rl", 1),
    "collectors": ("tar_rl.collectors", 2),
    "recipes": ("tar_rl.recipes", 3),
}
TOP = {"tar_rl.cli": 4, "tar_rl.__main__": 4}
OPEN = {"tar_rl"}  # importable from every layer (its __init__ imports objectives on first use)


def _modules() -> dict[str, Path]:
    out = {}
    for folder, (package, _) in FOLDERS.items():
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = path.relative_to(ROOT / folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            out[".".join([package, *parts])] = path
    return out


MODULES = _modules()


def layer(module: str) -> int | None:
    """The layer of a project module (None outside the project)."""
    if module in TOP:
        return TOP[module]
    best = None
    for package, level in FOLDERS.values():
        if module == package or module.startswith(package + "."):
            if best is None or len(package) > len(best[0]):
                best = (package, level)
    return None if best is None else best[1]


def _resolve(node: ast.ImportFrom, module: str, is_package: bool) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".") if is_package else module.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def imports(module: str, path: Path) -> list[tuple[int, str, list[str]]]:
    """``(line, imported module, names)`` of every import statement of a module, nested ones included."""
    tree = ast.parse(path.read_text(), filename=str(path))
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name, []) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            target = _resolve(node, module, path.name == "__init__.py")
            names = [a.name for a in node.names]
            out.append((node.lineno, target, names))
            # `from package import submodule` imports the submodule
            out += [(node.lineno, f"{target}.{n}", []) for n in names if f"{target}.{n}" in MODULES]
    return out


def _where(path: Path) -> str:
    return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)


def _violations() -> list[str]:
    found = []
    for module, path in MODULES.items():
        mine = layer(module)
        for line, target, names in imports(module, path):
            if target in OPEN or layer(target) is None or target.startswith(module + "."):
                continue
            if target in MODULES or any(target.startswith(p) for p, _ in FOLDERS.values()):
                theirs = layer(target)
                if theirs is not None and theirs > mine:
                    found.append(f"{_where(path)}:{line}: {module} (layer {mine}) imports {target} ({theirs})")
            private = [n for n in names if n.startswith("_") and not n.startswith("__")]
            if private and target != module:
                found.append(f"{_where(path)}:{line}: imports the private name(s) {private} of {target}")
    return found


def _private_attributes() -> list[str]:
    """``alias._name`` where ``alias`` is an imported project module."""
    found = []
    for module, path in MODULES.items():
        tree = ast.parse(path.read_text())
        aliases = {}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                for a in node.names:
                    if layer(a.name) is not None:
                        aliases[a.asname or a.name.split(".")[0]] = a.name
            elif isinstance(node, ast.ImportFrom):
                target = _resolve(node, module, path.name == "__init__.py")
                for a in node.names:
                    if f"{target}.{a.name}" in MODULES:
                        aliases[a.asname or a.name] = f"{target}.{a.name}"
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id in aliases
                and node.attr.startswith("_")
                and not node.attr.startswith("__")
            ):
                found.append(f"{_where(path)}:{node.lineno}: {aliases[node.value.id]}.{node.attr}")
    return found


def test_the_scan_sees_every_folder_and_resolves_relative_imports():
    assert {layer(m) for m in MODULES} >= {0, 1, 2, 3, 4}
    assert layer("tar_rl.objectives.tar_loss") == 0 and layer("tar_rl.data") == 1
    assert layer("tar_rl.collectors.dmc") == 2 and layer("tar_rl.recipes.config") == 3 and layer("tar_rl.cli") == 4
    node = ast.parse("from .config import X").body[0]
    assert _resolve(node, "tar_rl.recipes.offline_bc", False) == "tar_rl.recipes.config"
    node = ast.parse("from . import act").body[0]
    assert _resolve(node, "tar_rl.policies", True) == "tar_rl.policies"


def test_a_planted_upward_import_is_found(tmp_path, monkeypatch):
    fake = tmp_path / "objectives_fake.py"
    fake.write_text("def f():\n    from tar_rl.recipes import offline_bc\n    from tar_rl.data import _helper\n")
    monkeypatch.setitem(MODULES, "tar_rl.objectives.fake", fake)
    found = _violations()
    assert any("tar_rl.objectives.fake (layer 0) imports tar_rl.recipes" in v for v in found)
    assert any("private name(s) ['_helper'] of tar_rl.data" in v for v in found)


# The core's remaining imports of MetaWorld's collectors, listed so that no other one can be added and each
# entry goes when its import goes: the MetaWorld dataset builder still lives in tar_rl.data, and the policies
# still take MetaWorld's task count and instructions from tar_rl.collectors.metaworld.tasks.
KNOWN: set[tuple[str, str]] = set()


def test_imports_follow_the_layers():
    found = _violations()
    upward = {tuple(v.split(": ", 1)[1].replace(" imports ", "|").split("|")) for v in found if " (layer " in v}
    upward = {(a.split(" (layer")[0], b.split(" (")[0]) for a, b in upward}
    assert upward == KNOWN, "\n".join(found)
    assert [v for v in found if " (layer " not in v] == []


def test_no_module_reads_another_modules_private_names():
    found = _private_attributes()
    assert not found, "\n".join(found)


def test_no_module_rebinds_its_globals():
    """No function assigns module state (``global``): state lives in objects that their callers own."""
    found = [
        f"{_where(path)}:{node.lineno}: global {', '.join(node.names)}"
        for path in MODULES.values()
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.Global)
    ]
    assert not found, "\n".join(found)


def _leaf_violations() -> list[str]:
    """Imports of a project module outside ``tar_rl.objectives`` (``tar_rl`` itself included) by ``objectives``."""
    return [
        f"{_where(path)}:{line}: {module} imports {target}"
        for module, path in MODULES.items()
        if layer(module) == 0
        for line, target, _ in imports(module, path)
        if (target == "tar_rl" or target.startswith("tar_rl.")) and layer(target) != 0
    ]


def test_objectives_import_nothing_from_the_rest_of_the_package(monkeypatch, tmp_path):
    assert _leaf_violations() == []
    fake = tmp_path / "objectives_fake.py"
    fake.write_text(
        "import tar_rl\nfrom tar_rl.registry import Registry\nfrom tar_rl.objectives.tar import tar_weights\n"
    )
    monkeypatch.setitem(MODULES, "tar_rl.objectives.fake", fake)
    found = _leaf_violations()
    assert [v.split(": ", 1)[1] for v in found if "fake" in v] == [
        "tar_rl.objectives.fake imports tar_rl",
        "tar_rl.objectives.fake imports tar_rl.registry",
    ]
