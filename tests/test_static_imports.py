"""Type checkers and editors follow the package's layout: every module and every ``tar_rl`` import resolves.

pyproject.toml maps root folders into ``tar_rl`` (``objectives/`` -> ``tar_rl.objectives``). The editable
install carries that mapping in an import hook, which Python runs and static analysers cannot, so
``tar_rl/`` holds a link to each mapped root folder (``tar_rl/objectives`` -> ``../objectives``): a tool
reading the repository finds ``tar_rl.objectives.tar_loss`` at ``tar_rl/objectives/tar_loss.py``. mypy's
import resolution, run from the repository root without site-packages (so that only the repository's own
files count), checks it for every module of the package and every ``tar_rl`` import in them.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from paths import REPO

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: mypy's own dependency
    import tomli as tomllib

SETUPTOOLS = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
PACKAGE_DIR: dict[str, str] = SETUPTOOLS["package-dir"]
# An import that resolves nowhere, planted beside the package's own to show that the check reports one.
PLANTED = "tar_rl.objectives._planted_missing_module"
UNRESOLVED = re.compile(
    r'^(?P<where>.+?:\d+): error: Cannot find implementation or library stub for module named "(?P<module>[\w.]+)"'
)


def _modules() -> dict[str, Path]:
    """Every module of the package, by import name, from the folders pyproject.toml maps (links not followed)."""
    out = {}
    for package, folder in PACKAGE_DIR.items():
        for path in sorted((REPO / folder).rglob("*.py")):  # rglob does not descend into links
            rel = path.relative_to(REPO / folder).with_suffix("")
            out[".".join([package, *(p for p in rel.parts if p != "__init__")])] = path
    return out


def _package_folders() -> dict[str, Path]:
    """Every folder with an ``__init__.py`` under the mapped folders, by package name."""
    return {name: path.parent for name, path in _modules().items() if path.name == "__init__.py"}


def test_every_mapped_folder_has_its_link_in_tar_rl():
    missing = []
    for package, folder in PACKAGE_DIR.items():
        link = REPO / package.replace(".", "/")
        if link.resolve() != (REPO / folder).resolve():
            target = os.path.relpath(REPO / folder, link.parent)
            missing.append(f"{package} lives in {folder}/: ln -s {target} {link.relative_to(REPO)}")
    assert not missing, "type checkers and editors cannot find these packages:\n" + "\n".join(missing)


def test_every_package_folder_is_listed_in_pyproject():
    unlisted = sorted(set(_package_folders()) - set(SETUPTOOLS["packages"]))
    assert not unlisted, f"add {unlisted} to [tool.setuptools] packages in pyproject.toml (a wheel leaves them out)"


def test_mypy_resolves_every_module_and_tar_rl_import(tmp_path):
    if importlib.util.find_spec("mypy") is None:
        pytest.fail("mypy is missing: it comes with the test extra (pip install -e '.[test]')")
    modules = _modules()
    probe = tmp_path / "every_module.py"
    probe.write_text("".join(f"import {name}\n" for name in [*sorted(modules), PLANTED]))
    files = sorted(str(path.relative_to(REPO)) for path in modules.values())
    command = [sys.executable, "-m", "mypy", "--no-site-packages", "--follow-imports=skip", "--no-incremental"]
    command += ["--cache-dir", os.devnull, "--no-error-summary", "--hide-error-context", str(probe), *files]
    done = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode in (0, 1), done.stdout + done.stderr  # 1: errors found; 2: mypy could not run
    unresolved = [
        (m["where"], m["module"])
        for m in map(UNRESOLVED.match, done.stdout.splitlines())
        if m and m["module"].split(".")[0] == "tar_rl"
    ]
    assert (f"{probe}:{len(modules) + 1}", PLANTED) in unresolved, "the check no longer reports an unresolved import"
    found = sorted(f"{where}: {module}" for where, module in unresolved if module != PLANTED)
    assert not found, "type checkers do not resolve these tar_rl imports from the repository root:\n" + "\n".join(found)
