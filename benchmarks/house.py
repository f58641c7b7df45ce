"""The house's measures, read from the source (an AST scan): what issue 37 asks to report before and after.

``python -m benchmarks.house`` prints, for the repository it runs in:

* the lines of config handling (the recipe's config, validation and override modules), and of those the lines of
  code (not blank, not a comment, not inside a module's, class's or function's docstring), of docstrings (the
  documentation of each setting lives in these, so the code lines are the measure of how much handling there is),
  of comments and blank lines;
* every read of ``eval.rollouts`` (an attribute or a key named ``rollouts``) and of ``objective.gamma`` (``gamma``),
  by file, in the installed package (``objectives``, ``tar_rl``, ``collectors``, ``recipes``);
* the lines that use ``sys.path`` (the attribute, in code);
* per top-level folder, the largest module and the longest function (lines, decorators left out).

Import cycles are counted by ``tests/test_architecture.py``, which fails on any.
"""

from __future__ import annotations

import argparse
import ast
import io
import tokenize
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


def line_kinds(text: str) -> dict[str, int]:
    """The lines of a module by kind: ``docstrings`` (every line of a module's, class's or function's docstring),
    ``code`` (any other line with a token of code: a line of a multi-line string included), ``comments`` (a line with
    a comment and no code) and ``blank``."""
    owners = (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)
    docstrings = {
        line
        for node in ast.walk(ast.parse(text))
        if isinstance(node, owners) and ast.get_docstring(node, clean=False) is not None
        for line in range(node.body[0].lineno, node.body[0].end_lineno + 1)
    }
    layout = {tokenize.COMMENT, tokenize.NL, tokenize.NEWLINE, tokenize.INDENT, tokenize.DEDENT, tokenize.ENDMARKER}
    code = {
        line
        for token in tokenize.generate_tokens(io.StringIO(text).readline)
        if token.type not in layout
        for line in range(token.start[0], token.end[0] + 1)
    }
    kinds = Counter(code=0, docstrings=0, comments=0, blank=0)
    for number, line in enumerate(text.splitlines(), 1):
        if number in docstrings:
            kinds["docstrings"] += 1
        elif number in code:
            kinds["code"] += 1
        else:
            kinds["comments" if line.strip() else "blank"] += 1
    return dict(kinds)


def _functions(tree: ast.AST):
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            yield node.name, node.end_lineno - node.lineno + 1


def measure(root: Path = ROOT) -> dict:
    """The measures of the repository at ``root``."""
    config, config_kinds = {}, Counter(code=0, docstrings=0, comments=0, blank=0)
    for _, path, text in _sources(["recipes"], root):
        if path.stem in CONFIG:
            config[str(path.relative_to(root))] = len(text.splitlines())
            config_kinds.update(line_kinds(text))
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
    return {
        "config": config,
        "config_kinds": dict(config_kinds),
        "reads": reads,
        "syspath": syspath,
        "largest": largest,
        "longest": longest,
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.house", description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, default=ROOT, help="the repository to measure (default: this one)")
    m = measure(parser.parse_args(argv).root)
    kinds = ", ".join(f"{kind} {n}" for kind, n in m["config_kinds"].items())
    print(
        f"config handling: {sum(m['config'].values())} lines ({kinds}) "
        + ", ".join(f"{k} {v}" for k, v in m["config"].items())
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
