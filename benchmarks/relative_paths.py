"""Tracked files name paths relative to the repository, never the folders of the machine that wrote them.

Rewrites every absolute path in the repository's tracked plain-text files (:data:`TEXT_SUFFIXES`: a run's
``config.yaml`` and ``summary.json``, provenance, tables, reports) with :func:`tar_rl.runs.portable_path`, the
rule the writers of results use (``collect``, the benchmarks' provenance): ``data.root`` at ``/elsewhere/datasets``
becomes ``datasets``, a runs folder ``/elsewhere/study/runs`` becomes ``runs``, an output folder inside a checkout
becomes its path in the repository. A run's ``config.yaml`` and ``summary.json`` are read back after rewriting:
everything but their paths (:func:`tar_rl.runs.portable_summary`; no run's identity includes them) must be what
it was, so run names, results and the tables computed from them do not change. Compressed files, images and
checkpoints are not rewritten. Running it again changes nothing.

    python -m benchmarks.relative_paths [--check] [PATH ...]

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
#: An absolute path: a ``/`` that does not continue a word, a path, a glob or a placeholder (``<folder>``, ``{x}``),
#: and its components.
ABSOLUTE = re.compile(r"(?<![\w.~$}>*/-])/[\w.+@-]+(?:/[\w.+@-]+)*")


def rewrite(text: str, root: Path = REPO, known: dict[str, str] | None = None) -> tuple[str, list[str]]:
    """``text`` with its absolute paths written relative to the repository ``root`` (those in ``known`` as it says,
    the others by :func:`tar_rl.runs.portable_path`), and the paths it cannot place (left as they are)."""
    unplaced: list[str] = []

    def relative(match: re.Match) -> str:
        path = match.group()
        if known and path in known:
            return known[path]
        try:
            return runs.portable_path(path, root)
        except ValueError:
            unplaced.append(path)
            return path

    return ABSOLUTE.sub(relative, text), unplaced


def _portable_run_file(name: str, text: str, root: Path):
    """A run's ``config.yaml`` or ``summary.json`` as read, and as a tracked copy records it (None, None for
    other files)."""
    if name == runs.CONFIG_FILE:
        before = yaml.safe_load(text)
        return before, runs.portable_config(before, root) if isinstance(before, dict) else before
    if name == runs.SUMMARY_FILE:
        before = json.loads(text)
        return before, runs.portable_summary(before, root) if isinstance(before, dict) else before
    return None, None


def _changed_strings(before, after) -> dict[str, str]:
    if isinstance(before, dict) and isinstance(after, dict):
        return {k: v for key in before for k, v in _changed_strings(before[key], after.get(key)).items()}
    return {before: after} if isinstance(before, str) and isinstance(after, str) and before != after else {}


def run_file_paths(name: str, text: str, root: Path = REPO) -> dict[str, str]:
    """The paths a run's ``config.yaml`` or ``summary.json`` records, each with what
    :func:`tar_rl.runs.portable_config` and :func:`tar_rl.runs.portable_summary` write for it (empty for other
    files): a ``data.root`` in no folder of a checkout is ``datasets`` there, which :func:`rewrite` alone cannot
    tell."""
    before, after = _portable_run_file(name, text, root)
    return _changed_strings(before, after)


def check_run_file(name: str, old: str, new: str, root: Path = REPO) -> None:
    """Refuse a rewritten run ``config.yaml`` or ``summary.json`` that differs from the original in anything but
    the paths :func:`tar_rl.runs.portable_config` and :func:`tar_rl.runs.portable_summary` write relative to
    ``root``.

    Raises:
        ValueError: naming the file when it does.
    """
    if name not in (runs.CONFIG_FILE, runs.SUMMARY_FILE):
        return
    _, expected = _portable_run_file(name, old, root)
    after = yaml.safe_load(new) if name == runs.CONFIG_FILE else json.loads(new)
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
        try:
            known = run_file_paths(path.name, old)
        except ValueError as err:
            unplaced.append(f"{rel}: {err}")
            continue
        new, missed = rewrite(old, REPO, known)
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
