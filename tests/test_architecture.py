"""The import direction of the package, enforced on the source (an AST scan of every module).

Layers, lowest first: ``objectives`` (the loss, a leaf) <- the core (``tar_rl`` itself: data
format, policies, runs, metrics, reports, importers) <- ``collectors`` (simulator suites) <-
``recipes`` <- the command line (``tar_rl.cli``, ``tar_rl.__main__``); the benchmark scripts sit on
top. A module may import its own layer and the layers below it, never above, wherever the import
statement is (module level or inside a function). The registry class lives in the leaf
(``tar_rl.objectives.registry``), so that ``objectives`` imports nothing from the rest of the package;
the package's ``__init__`` re-exports objectives lazily.
No module imports another module's private name (``from m import _x`` or ``m._x``).

Over the whole repository (the package, ``benchmarks/``, the tests, ``docs/``, the LeRobot plugin): no import cycle,
between modules or between packages, counting the imports inside functions; and no code changes ``sys.path``
(a module is run with ``python -m`` from the repository root, or loaded from its file, instead).
"""

from __future__ import annotations

import ast
import itertools
import subprocess
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


# -- The whole repository: import cycles and sys.path ----------------------------------------------------------

# Where Python imports the repository's files from: a folder of a package (its modules named under the package), or
# a folder of scripts and tests (each file a top-level module named by its stem, as pytest and `python FILE` import
# them; an import from one looks in its own folder first).
PACKAGES = {**{folder: package for folder, (package, _) in FOLDERS.items()}, "benchmarks": "benchmarks"}
PACKAGES["lerobot_policy_tar/src/lerobot_policy_tar"] = "lerobot_policy_tar"
SCRIPTS = ("tests", "lerobot_policy_tar/tests", "docs")


def _repository() -> dict[str, Path]:
    """Every Python file of the repository by the name it is imported as (``folder:stem`` for a script folder's)."""
    out = {}
    for folder, package in PACKAGES.items():
        for path in sorted((ROOT / folder).rglob("*.py")):  # rglob does not descend into links (tar_rl/objectives)
            rel = path.relative_to(ROOT / folder).with_suffix("")
            out[".".join([package, *(p for p in rel.parts if p != "__init__")])] = path
    for folder in SCRIPTS:
        for path in sorted((ROOT / folder).rglob("*.py")):
            out[f"{folder}:{path.stem}"] = path
    return out


REPOSITORY = _repository()


def _script_folder(module: str) -> str | None:
    return module.split(":")[0] if ":" in module else None


def _find(name: str, importer: str) -> str | None:
    """The repository module an import of ``name`` from ``importer`` loads: the importer's own script folder first,
    then the packages; a name inside a module (``a.b.f``) is its module (``a.b``); ``None`` outside the repository.
    The parent packages an import runs first are not counted (each module's package is)."""
    folder = _script_folder(importer)
    while name:
        if folder is not None and f"{folder}:{name}" in REPOSITORY:
            return f"{folder}:{name}"
        if name in REPOSITORY:
            return name
        name = name.rpartition(".")[0]
    return None


def import_graph() -> dict[str, dict[str, str]]:
    """``{module: {imported repository module: where its first import is (file:line)}}`` over every import
    statement, the ones inside functions included (``from package import name`` imports the submodule
    ``package.name`` where there is one, else the package)."""
    graph: dict[str, dict[str, str]] = {}
    for module, path in REPOSITORY.items():
        edges = graph.setdefault(module, {})
        package = module.split(":")[-1]
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = _resolve(node, package, path.name == "__init__.py")
                names = [f"{base}.{a.name}" for a in node.names]  # _find walks up to the package
            else:
                continue
            for name in names:
                target = _find(name, module)
                if target is not None and target != module:
                    edges.setdefault(target, f"{_where(path)}:{node.lineno}")
    return graph


def package_graph(graph: dict[str, dict[str, str]]) -> dict[str, dict[str, str]]:
    """The import graph between packages (a module's package: its folder's), leaving out the imports between a
    package and the packages inside it (``tar_rl`` and ``tar_rl.data``)."""

    def package(module: str) -> str:
        folder = _script_folder(module)
        if folder is not None:
            return folder
        return module if REPOSITORY[module].name == "__init__.py" else module.rpartition(".")[0]

    out: dict[str, dict[str, str]] = {}
    for module, edges in graph.items():
        mine = package(module)
        for target, where in edges.items():
            theirs = package(target)
            if mine != theirs and not theirs.startswith(mine + ".") and not mine.startswith(theirs + "."):
                out.setdefault(mine, {}).setdefault(theirs, where)
                out.setdefault(theirs, {})
    return out


def cycles(graph: dict[str, dict[str, str]]) -> list[list[str]]:
    """The strongly connected components of ``graph`` with more than one node (Tarjan's algorithm), each sorted;
    a graph without them has no cycle."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for target in graph.get(node, {}):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def describe_cycle(component: list[str], graph: dict[str, dict[str, str]]) -> str:
    """One cycle through a component, each import with where it is: ``a -> b (a.py:12) -> a (b.py:40)``."""
    start, members = component[0], set(component)
    paths = {start: [start]}
    queue = [start]
    while queue:  # breadth first, within the component, back to the start
        node = queue.pop(0)
        for target in sorted(graph[node]):
            if target == start:
                path = [*paths[node], start]
                return " -> ".join([start, *(f"{n} ({graph[m][n]})" for m, n in itertools.pairwise(path))])
            if target in members and target not in paths:
                paths[target] = [*paths[node], target]
                queue.append(target)
    raise AssertionError(f"{component} holds no cycle")


def _sys_path_changes(path: Path) -> list[str]:
    """The statements of a file that change the import path, in line order: ``sys.path.insert(...)`` and its kin,
    an assignment to ``sys.path`` or an item of it, ``monkeypatch.syspath_prepend`` and ``site.addsitedir``."""

    def is_sys_path(node: ast.AST) -> bool:
        return isinstance(node, ast.Attribute) and node.attr == "path" and _is_name(node.value, "sys")

    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        targets = []
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            if is_sys_path(node.func.value) or node.func.attr in ("syspath_prepend", "addsitedir"):
                found.append((node.lineno, f"{ast.unparse(node.func)}(...)"))
        elif isinstance(node, (ast.Assign, ast.AugAssign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
        elif isinstance(node, ast.Delete):
            targets = node.targets
        for target in targets:
            if is_sys_path(target) or (isinstance(target, ast.Subscript) and is_sys_path(target.value)):
                found.append((node.lineno, f"{ast.unparse(target)} changed"))
    return [f"{_where(path)}:{line}: {what}" for line, what in sorted(found)]


def _is_name(node: ast.AST, name: str) -> bool:
    return isinstance(node, ast.Name) and node.id == name


_LINKS = [Path(p.replace(".", "/")) for p, _ in FOLDERS.values() if p != "tar_rl"]  # tar_rl/objectives -> objectives


def test_the_repository_scan_sees_every_tracked_python_file():
    tracked = subprocess.run(["git", "ls-files", "*.py"], cwd=ROOT, capture_output=True, text=True, check=True)
    files = {ROOT / name for name in tracked.stdout.split()}
    files = {f for f in files if f.is_file() and not any(ROOT / link in f.parents for link in _LINKS)}
    seen = set(REPOSITORY.values())
    assert len(seen) == len(REPOSITORY), "two files are imported by the same name"
    assert sorted(map(_where, files - seen)) == [], "add their folder to PACKAGES or SCRIPTS"


def test_no_import_cycle_between_modules():
    graph = import_graph()
    found = [describe_cycle(c, graph) for c in cycles(graph)]
    assert not found, "import cycles (one cycle per group of modules that import each other):\n" + "\n".join(found)


def test_no_import_cycle_between_packages():
    graph = package_graph(import_graph())
    found = [describe_cycle(c, graph) for c in cycles(graph)]
    assert not found, "packages that import each other:\n" + "\n".join(found)


def test_no_code_changes_sys_path():
    found = [change for path in REPOSITORY.values() for change in _sys_path_changes(path)]
    assert not found, "run the module with `python -m` from the repository root, or load it from its file:\n" + (
        "\n".join(found)
    )


def test_a_planted_cycle_through_a_function_level_import_is_found(tmp_path, monkeypatch):
    (tmp_path / "one.py").write_text("from benchmarks.fake import two\n")
    (tmp_path / "two.py").write_text("def f():\n    from benchmarks.fake.one import f\n")
    (tmp_path / "three.py").write_text("from paths import REPO\nfrom benchmarks.fake.one import x\n")
    (tmp_path / "__init__.py").write_text("")
    for name in ("one", "two"):
        monkeypatch.setitem(REPOSITORY, f"benchmarks.fake.{name}", tmp_path / f"{name}.py")
    monkeypatch.setitem(REPOSITORY, "benchmarks.fake", tmp_path / "__init__.py")
    monkeypatch.setitem(REPOSITORY, "tests:three", tmp_path / "three.py")
    graph = import_graph()
    three = f"{tmp_path / 'three.py'}"
    assert graph["tests:three"] == {"tests:paths": f"{three}:1", "benchmarks.fake.one": f"{three}:2"}  # by stem
    assert list(graph["benchmarks.fake.one"]) == ["benchmarks.fake.two"]  # the submodule, not the package
    found = [describe_cycle(c, graph) for c in cycles(graph)]
    one, two = tmp_path / "one.py", tmp_path / "two.py"
    assert f"benchmarks.fake.one -> benchmarks.fake.two ({one}:1) -> benchmarks.fake.one ({two}:2)" in found


def test_a_planted_cycle_between_packages_is_found(tmp_path, monkeypatch):
    (tmp_path / "a.py").write_text("from benchmarks.pkg_b.b import x\n")
    (tmp_path / "b.py").write_text("import benchmarks.pkg_a.a\n")
    monkeypatch.setitem(REPOSITORY, "benchmarks.pkg_a.a", tmp_path / "a.py")
    monkeypatch.setitem(REPOSITORY, "benchmarks.pkg_b.b", tmp_path / "b.py")
    graph = package_graph(import_graph())
    found = [describe_cycle(c, graph) for c in cycles(graph)]
    a, b = tmp_path / "a.py", tmp_path / "b.py"
    assert f"benchmarks.pkg_a -> benchmarks.pkg_b ({a}:1) -> benchmarks.pkg_a ({b}:1)" in found


def test_planted_sys_path_changes_are_found(tmp_path):
    fake = tmp_path / "fake.py"
    fake.write_text(
        "import sys\nsys.path.insert(0, 'x')\nsys.path.append('y')\nsys.path[0] = 'z'\nsys.path = []\n"
        "sys.path += ['w']\n\ndef test(monkeypatch):\n    monkeypatch.syspath_prepend('v')\n"
        "print(sys.path)\nimport os.path\nos.path.join('a')\n"
    )
    assert [c.split(": ", 1)[1] for c in _sys_path_changes(fake)] == [
        "sys.path.insert(...)",
        "sys.path.append(...)",
        "sys.path[0] changed",
        "sys.path changed",
        "sys.path changed",
        "monkeypatch.syspath_prepend(...)",
    ]
