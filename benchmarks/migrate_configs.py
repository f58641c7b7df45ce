"""Committed runs' configs in the format of this version: each objective section lists its weighting's parameters.

tar-rl versions before each weighting owned its parameters saved every registered weighting's parameters in every
run's objective section. This rewrites the tracked ``config.yaml`` files of runs and the config a ``summary.json``
holds with :func:`tar_rl.recipes.rundir.migrate_config`: the parameters of other weightings at their defaults are
dropped, nothing else changes (the files are written as the study's ``collect`` writes them: YAML in the config's
order, JSON indented by one). Each run's name is computed again from its rewritten config and must be its folder's
name and its summary's ``run_name``, so run names and the tables computed from the runs do not change. A
checkpoint's config is not rewritten (the file the R1 runs start from stays as it is): ``init.from`` reads it
through the same migration. Running it again changes nothing.

    python -m benchmarks.migrate_configs [--check] [PATH ...]

``PATH`` limits it to the tracked files under those paths (default: ``benchmarks/results``). ``--check`` writes
nothing and exits 1 naming the files that would change.
"""

from __future__ import annotations

import argparse
import json
import subprocess
from collections.abc import Sequence
from pathlib import Path

import yaml

from tar_rl import runs
from tar_rl.io import atomic_write
from tar_rl.recipes.rundir import migrate_config, run_name

REPO = Path(__file__).resolve().parent.parent


def migrate_text(name: str, text: str) -> str:
    """A run's ``config.yaml`` or ``summary.json`` (by its file ``name``) with its config migrated; other files and
    files already in this version's format come back as they are."""
    if name == runs.CONFIG_FILE:
        config = yaml.safe_load(text)
        new = migrate_config(config) if isinstance(config, dict) else config
        return text if new == config else yaml.safe_dump(new, sort_keys=False)
    if name == runs.SUMMARY_FILE:
        summary = json.loads(text)
        config = summary.get("config") if isinstance(summary, dict) else None
        if not isinstance(config, dict) or migrate_config(config) == config:
            return text
        return json.dumps({**summary, "config": migrate_config(config)}, indent=1)
    return text


def check_run_name(path: Path, text: str) -> None:
    """Refuse a migrated run file whose config no longer names its run folder (or its summary's ``run_name``).

    Raises:
        ValueError: naming the name it computes and the one it should.
    """
    data = yaml.safe_load(text) if path.name == runs.CONFIG_FILE else json.loads(text)
    config = data if path.name == runs.CONFIG_FILE else data.get("config")
    if not isinstance(config, dict) or path.parent.parent.name != "runs":
        return
    expected = data.get("run_name", path.parent.name) if path.name == runs.SUMMARY_FILE else path.parent.name
    name = run_name(config)
    if name != expected:
        raise ValueError(f"its migrated config names the run {name}, not {expected}")


def tracked_run_files(paths: Sequence[str], root: Path = REPO) -> list[Path]:
    """The tracked ``config.yaml`` and ``summary.json`` files under ``paths``."""
    out = subprocess.run(["git", "ls-files", "-z", "--", *paths], cwd=root, capture_output=True, check=True).stdout
    files = [root / name for name in out.decode().split("\0") if name]
    return [f for f in files if f.name in (runs.CONFIG_FILE, runs.SUMMARY_FILE) and f.is_file()]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point (module docstring). Returns 0, or 1 with ``--check`` when a file would change."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="*", metavar="PATH", help="limit to the tracked files under these paths")
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 naming the files that change")
    args = parser.parse_args(argv)
    changed = []
    for path in tracked_run_files(args.paths or ["benchmarks/results"]):
        rel = path.relative_to(REPO).as_posix()
        old = path.read_text()
        new = migrate_text(path.name, old)
        if new == old:
            continue
        try:
            check_run_name(path, new)
        except ValueError as err:
            raise SystemExit(f"migrate_configs: {rel}: {err}") from None
        changed.append(rel)
        if not args.check:
            atomic_write(path, lambda f, new=new: f.write(new))
    verb = "would change" if args.check else "changed"
    print(f"{len(changed)} file(s) {verb}" + "".join(f"\n  {rel}" for rel in changed[:20]))
    if len(changed) > 20:
        print(f"  ... and {len(changed) - 20} more")
    return int(args.check and bool(changed))


if __name__ == "__main__":
    raise SystemExit(main())
