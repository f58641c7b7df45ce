"""The house's measures, read from the source (an AST scan): what issue 37 asks to report before and after.

``python -m benchmarks.house`` prints, for the repository it runs in:

* the lines of config handling (the recipe's config, validation and override modules);
* every read of ``eval.rollouts`` (an attribute or a key named ``rollouts``) and of ``objective.gamma`` (``gamma``),
  by file, in the installed package (``objectives``, ``tar_rl``, ``collectors``, ``recipes``);
* the lines that use ``sys.path`` (the attribute, in code);
* per top-level folder, the largest module and the longest function (lines, decorators left out).

Import cycles are counted by ``tests/test_architecture.py``, which fails on any.
"""

from __future__ import annotations

import argparse
import ast
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ("objectives", "tar_rl", "collectors", "recipes")
FOLDERS = (*PACKAGE, "benchmarks", "lerobot_policy_tar", "tests", "docs")
CONFIG = ("config", "validate", "overrides", "sections", "evalspec")


def _sources(folders, root: Path):
    for folder in folders:
        for path in sorted((root / folder).rglob("*.py")):
            if ".venv" not in path.parts:
                yield folder, path, path.read_text()


def _reads(tree: ast.AST, name: str) -> int:
    """Attribute reads ``x.<name>`` and subscripts ``x["<name>"]``."""
    count = 0
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr == name and isinstance(node.ctx, ast.Load):
            count += 1
        elif isinstance(node, ast.Subscript) and isinstance(node.slice, ast.Constant) and node.slice.value == name:
            count += 1
    return count


def _functions(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node.name, node.end_lineno - node.lineno + 1


def measure(root: Path = ROOT) -> dict:
    """The measures of the repository at ``root``."""
    config = {
        str(p.relative_to(root)): len(text.splitlines())
        for _, p, text in _sources(["recipes"], root)
        if p.stem in CONFIG
    }
    reads = {"rollouts": Counter(), "gamma": Counter()}
    syspath = []
    largest, longest = {}, {}
    for folder, path, text in _sources(FOLDERS, root):
        rel = str(path.relative_to(root))
        tree = ast.parse(text)
        if folder in PACKAGE:
            for name in reads:
                if n := _reads(tree, name):
                    reads[name][rel] += n
        syspath += [
            f"{rel}:{node.lineno}"
            for node in ast.walk(tree)
            if isinstance(node, ast.Attribute) and node.attr == "path" and getattr(node.value, "id", None) == "sys"
        ]
        lines = len(text.splitlines())
        if lines > largest.get(folder, ("", 0))[1]:
            largest[folder] = (rel, lines)
        for fn, n in _functions(tree):
            if n > longest.get(folder, ("", 0))[1]:
                longest[folder] = (f"{rel}:{fn}", n)
    return {"config": config, "reads": reads, "syspath": syspath, "largest": largest, "longest": longest}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.house", description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=ROOT, help="the repository to measure (default: this one)")
    m = measure(parser.parse_args(argv).root)
    print(
        f"config handling: {sum(m['config'].values())} lines " + ", ".join(f"{k} {v}" for k, v in m["config"].items())
    )
    for name, counter in m["reads"].items():
        print(
            f"reads of {name}: {sum(counter.values())} in {len(counter)} files: "
            + ", ".join(f"{k} {v}" for k, v in counter.most_common())
        )
    print(f"sys.path lines: {len(m['syspath'])}" + "".join(f"\n  {s}" for s in m["syspath"]))
    for folder in FOLDERS:
        if folder in m["largest"]:
            (mod, lines), (fn, n) = m["largest"][folder], m["longest"][folder]
            print(f"{folder}: largest module {mod} ({lines} lines); longest function {fn} ({n} lines)")


if __name__ == "__main__":
    main()
