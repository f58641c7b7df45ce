"""Tracked files name paths relative to the repository, never the folders of the machine that wrote them.

Rewrites every absolute path in the repository's tracked plain-text files (:data:`TEXT_SUFFIXES`: a run's
``config.yaml`` and ``summary.json``, provenance, tables, reports) with :func:`tar_rl.runs.portable_path`, the
rule the writers of results use (``collect``, the benchmarks' provenance): ``data.root`` at ``/elsewhere/datasets``
becomes ``datasets``, a runs folder ``/elsewhere/study/runs`` becomes ``runs``, an output folder inside a checkout
becomes its path in the repository. A run's ``config.yaml`` and ``summary.json`` are read back after rewriting:
everything but their paths (:func:`tar_rl.runs.portable_summary`; no run's identity includes them) must be what
it was, so run names, results and the tables computed from them do not change. Compressed files, images and
checkpoints are not rewritten. Running it again changes nothing.

    python benchmarks/relative_paths.py [--check] [PATH ...]

``PATH`` limits it to the tracked files under those paths (default: the whole repository). ``--check`` writes
nothing and exits 1 naming the files that would change. A path it cannot place (outside the repository and in
none of a checkout's folders) is named and the exit status is 1.
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path

import yaml

from tar_rl import runs
from tar_rl.io import atomic_write

REPO = Path(__file__).resolve().parent.parent
#: The plain-text files it rewrites.
TEXT_SUFFIXES = (".yaml", ".yml", ".json", ".md", ".csv", ".txt")
#: An absolute path: a ``/`` that does not continue a word, a path or a placeholder (``<folder>``, ``{x}``), and
#: two or more components.
ABSOLUTE = re.compile(r"(?<![\w.~$}>/-])/[\w.+@-]+(?:/[\w.+@-]+)+")


def rewrite(text: str, root: Path = REPO) -> tuple[str, list[str]]:
    """``text`` with its absolute paths written relative to the repository ``root``, and the paths it cannot
    place (left as they are)."""
    unplaced: list[str] = []

    def relative(match: re.Match) -> str:
        try:
            return runs.portable_path(match.group(), root)
        except ValueError:
            unplaced.append(match.group())
            return match.group()

    return ABSOLUTE.sub(relative, text), unplaced


def check_run_file(name: str, old: str, new: str, root: Path = REPO) -> None:
    """Refuse a rewritten run ``config.yaml`` or ``summary.json`` that differs from the original in anything but
    the paths :func:`tar_rl.runs.portable_config` and :func:`tar_rl.runs.portable_summary` write relative to
    ``root``.

    Raises:
        ValueError: naming the file when it does.
    """
    if name == runs.CONFIG_FILE:
        before, after = yaml.safe_load(old), yaml.safe_load(new)
        expected = runs.portable_config(before, root) if isinstance(before, dict) else before
    elif name == runs.SUMMARY_FILE:
        before, after = json.loads(old), json.loads(new)
        expected = runs.portable_summary(before, root) if isinstance(before, dict) else before
    else:
        return
    if after != expected:
        raise ValueError("rewriting its paths would change more than the paths a run's files record")


def tracked_text_files(paths: Sequence[str], root: Path = REPO) -> list[Path]:
    """The tracked files of :data:`TEXT_SUFFIXES` under ``paths`` (every one without)."""
    out = subprocess.run(["git", "ls-files", "-z", "--", *paths], cwd=root, capture_output=True, check=True).stdout
    files = [root / name for name in out.decode().split("\0") if name]
    return [f for f in files if f.suffix in TEXT_SUFFIXES and f.is_file()]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (module docstring). Returns 0, or 1 with ``--check`` when a file would change, or when a
    path cannot be placed."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="*", metavar="PATH", help="limit to the tracked files under these paths")
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 naming the files that change")
    args = parser.parse_args(argv)
    changed, unplaced = [], []
    for path in tracked_text_files(args.paths):
        rel = path.relative_to(REPO).as_posix()
        try:
            old = path.read_bytes().decode("utf-8")
        except UnicodeDecodeError:
            continue  # not plain text
        new, missed = rewrite(old)
        unplaced += [f"{rel}: {p}" for p in missed]
        if new == old:
            continue
        try:
            check_run_file(path.name, old, new)
        except ValueError as err:
            raise SystemExit(f"relative_paths: {rel}: {err}") from None
        changed.append(rel)
        if not args.check:
            data = new.encode("utf-8")
            atomic_write(path, lambda f, data=data: f.write(data), binary=True)
    verb = "would change" if args.check else "changed"
    print(f"{len(changed)} file(s) {verb}" + "".join(f"\n  {rel}" for rel in changed))
    if unplaced:
        print(f"{len(unplaced)} path(s) outside the repository and its folders, left as they are:", file=sys.stderr)
        print("\n".join(f"  {u}" for u in unplaced), file=sys.stderr)
    return int(bool(unplaced) or (args.check and bool(changed)))


if __name__ == "__main__":
    raise SystemExit(main())
