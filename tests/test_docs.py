"""The documentation as a newcomer meets it: generated pages fresh, examples running, links resolving, no paths
outside the repository (docs/contributing.md describes the conventions)."""

from __future__ import annotations

import contextlib
import gzip
import importlib.util
import io
import re
import shlex
import subprocess
from dataclasses import dataclass
from pathlib import Path

import pytest
from paths import REPO

# The pages whose code blocks are examples: the README and docs/.
PAGES = sorted([REPO / "README.md", *(REPO / "docs").glob("*.md")])
SKIP = re.compile(r"<!--\s*skip:\s*(\S.*?)\s*-->")
RUN_WITH = re.compile(r"<!--\s*run-with:\s*(.+?)\s+=>\s+(.+?)\s*-->")


@dataclass
class Block:
    page: Path
    line: int  # of the opening fence, 1-based
    lang: str
    code: str
    marker: str  # the HTML comment on the line before the fence, or ""

    @property
    def where(self) -> str:
        return f"{self.page.relative_to(REPO)}:{self.line}"


def code_blocks(page: Path) -> list[Block]:
    """The fenced code blocks of a Markdown page, with the marker comment on the line before each."""
    blocks, lines = [], page.read_text().splitlines()
    i = 0
    while i < len(lines):
        fence = re.match(r"^```(\w*)\s*$", lines[i])
        if not fence:
            i += 1
            continue
        end = next(j for j in range(i + 1, len(lines)) if lines[j].startswith("```"))
        marker = lines[i - 1].strip() if i and lines[i - 1].strip().startswith("<!--") else ""
        blocks.append(Block(page, i + 1, fence.group(1), "\n".join(lines[i + 1 : end]) + "\n", marker))
        i = end + 1
    return blocks


BLOCKS = [b for page in PAGES for b in code_blocks(page)]


def _skipped(block: Block) -> bool:
    return bool(SKIP.match(block.marker))


# -- Generated files ----------------------------------------------------------------------------


def _generator():
    spec = importlib.util.spec_from_file_location("docs_generate", REPO / "docs" / "generate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_generated_files_are_what_the_generator_writes():
    stale = _generator().stale()
    assert not stale, f"{stale} differ from what the generator writes: run `python docs/generate.py`"


def test_config_reference_lists_every_field():
    """Every field of every section and head is a row of the page (the generator reads the dataclasses)."""
    import dataclasses

    from tar_rl.policies import POLICIES
    from tar_rl.recipes import config as cfg

    page = (REPO / "docs" / "config.md").read_text()
    sections = {"objective": cfg.ObjectiveConfig, "data": cfg.DataConfig, "eval": cfg.EvalConfig}
    sections |= {"optim": cfg.OptimConfig, "logging": cfg.LoggingConfig, "diagnostics": cfg.DiagnosticsConfig}
    keys = [f"{s}.{f.name}" for s, c in sections.items() for f in dataclasses.fields(c)]
    keys += [f"policy.{f.name}" for spec in POLICIES.values() for f in dataclasses.fields(spec.config)]
    keys += ["seed", "threads", "device", "runs_root", "run_dir", "init.from"]
    missing = [k for k in keys if f"| `{k}` |" not in page]
    assert not missing, f"docs/config.md lacks {missing}: run `python docs/generate.py`"


# -- Python examples ----------------------------------------------------------------------------

PYTHON = [b for b in BLOCKS if b.lang == "python"]


@pytest.mark.parametrize("block", PYTHON, ids=[b.where for b in PYTHON])
def test_python_example_runs(block: Block, tmp_path, monkeypatch):
    if _skipped(block):
        pytest.skip(SKIP.match(block.marker).group(1))
    code = block.code
    replace = RUN_WITH.match(block.marker)
    if replace:
        old, new = replace.groups()
        assert old in code, f"{block.where}: the run-with marker's {old!r} is not in the block"
        code = code.replace(old, new)
    monkeypatch.chdir(tmp_path)
    exec(compile(code, block.where, "exec"), {"__name__": "__docs_example__"})


# -- tar-rl command lines -----------------------------------------------------------------------


def command_lines(block: Block) -> list[list[str]]:
    """The ``tar-rl`` argument lists of a bash block (``tar-rl ...``, ``python -m tar_rl ...``, ``torchrun ... -m
    tar_rl ...``), comments and continuation lines handled, a trailing ``...`` dropped."""
    commands = []
    for line in block.code.replace("\\\n", " ").splitlines():
        for part in re.split(r"\s*&&\s*", line):
            words = shlex.split(part, comments=True)
            if words and Path(words[0]).name == "tar-rl":
                args = words[1:]
            elif "tar_rl" in words and words.index("tar_rl") > 0 and words[words.index("tar_rl") - 1] == "-m":
                args = words[words.index("tar_rl") + 1 :]
            else:
                continue
            commands.append([a for a in args if a not in ("...", "--debug")])
    return commands


COMMANDS = [(b, c) for b in BLOCKS if b.lang == "bash" and not _skipped(b) for c in command_lines(b)]


def _run(argv: list[str]) -> tuple[int, str]:
    """``tar-rl argv`` in this process: its exit status and what it printed."""
    from tar_rl.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        try:
            status = main(argv) or 0
        except SystemExit as exit_:
            status = exit_.code if isinstance(exit_.code, int) else 1
    return status, out.getvalue()


def _train_jobs(args: list[str]) -> list[list[str]]:
    """The single jobs that check a ``tar-rl train`` line with ``--cfg job``: a ``-m`` sweep is checked at the first
    and at the last value of every swept key."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    options, overrides, words = [], [], iter(a for a in args if a not in ("-m", "--multirun"))
    for word in words:
        if word.startswith("-"):
            options += [word, next(words)] if word in ("--cfg", "--config-dir", "-cd", "--config-name") else [word]
        else:
            overrides.append(word)
    if "--cfg" not in options:
        options += ["--cfg", "job"]
    parsed = OverridesParser.create().parse_overrides(overrides) if overrides else []
    # Per override its choices as single overrides: the swept values of a sweep, else the override itself.
    choices = [
        [f"{o.get_key_element()}={v}" for v in o.sweep_string_iterator()] if o.is_sweep_override() else [o.input_line]
        for o in parsed
    ]
    first = [c[0] for c in choices]
    last = [c[-1] for c in choices]
    jobs = [first] if first == last else [first, last]
    return [["train", *options, *job] for job in jobs]


def _help_path(args: list[str]) -> list[str]:
    """The sub-commands at the start of ``args`` (``data import robomimic``), as the parser knows them."""
    import argparse

    from tar_rl.cli import _parser

    parser, path = _parser(), []
    for word in args:
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        if not subs or word not in subs[0].choices:
            break
        path.append(word)
        parser = subs[0].choices[word]
    return path


@pytest.mark.parametrize("block, args", COMMANDS, ids=[f"{b.where}:{' '.join(c)[:60]}" for b, c in COMMANDS])
def test_command_line_parses(block: Block, args: list[str], monkeypatch):
    monkeypatch.chdir(REPO)  # --config-dir and other relative paths as a reader runs them
    if args and args[0] == "train":
        for job in _train_jobs(args[1:]):
            status, printed = _run(job)
            assert status == 0 and "objective:" in printed, f"{block.where}: tar-rl {' '.join(job)}\n{printed}"
        return
    path = _help_path(args) or args[:1]
    status, printed = _run([*path, "--help"])
    assert status == 0, f"{block.where}: tar-rl {' '.join(path)} --help\n{printed}"
    unknown = [a.split("=")[0] for a in args if a.startswith("--") and a.split("=")[0] not in printed]
    assert not unknown, f"{block.where}: tar-rl {' '.join(path)} has no option(s) {unknown}"


# -- Links --------------------------------------------------------------------------------------


def tracked_files() -> list[Path]:
    """The repository's files: tracked, and new ones git does not ignore."""
    command = ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"]
    try:
        listed = subprocess.run(command, cwd=REPO, capture_output=True, check=True, timeout=60)
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    return [REPO / p for p in listed.stdout.decode().split("\0") if p]


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces as hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.S | re.M)
    seen: dict[str, int] = {}
    out = set()
    for heading in re.findall(r"^#{1,6}\s+(.+?)\s*#*\s*$", text, flags=re.M):
        base = slug(heading)
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def test_relative_links_resolve():
    broken = []
    for page in (p for p in tracked_files() if p.suffix == ".md" and p.is_file()):
        text = re.sub(r"^```.*?^```", "", page.read_text(), flags=re.S | re.M)
        for target in re.findall(r"\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)", text):
            if re.match(r"^[a-z]+:", target):  # http:, https:, mailto:
                continue
            path, _, anchor = target.partition("#")
            resolved = (page.parent / path).resolve() if path else page
            where = f"{page.relative_to(REPO)} -> {target}"
            if not resolved.exists():
                broken.append(f"{where}: no such file")
            elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
                broken.append(f"{where}: no heading with that anchor")
    assert not broken, "\n".join(broken)


# -- Paths outside the repository ---------------------------------------------------------------

# A parent folder's files, or an absolute path of a machine (home folders, mounts, scratch and temporary folders).
OUTSIDE = re.compile(r"\.\./shared\b|(?<![\w.~$}])/(?:work|home|Users|root|mnt|scratch|tmp)/")
# Files that show a machine's path where no rewrite reaches, each with the reason (benchmarks/relative_paths.py
# rewrites the plain-text ones); the test checks that each is still tracked.
MACHINE_PATH_KEPT = {
    "benchmarks/results/paper-cpu/budget/budget.png": "its footer shows its command's paths as pixels, and the "
    "runs that would draw it again are not committed",
    "benchmarks/results/paper-cpu/sensitivity/sensitivity.png": "the same: its footer, as pixels",
    "benchmarks/results/regimes/runs/uniform-mlp-s0-b38746e7/checkpoint.pt": "R1's source: its stored config "
    "names its folders, and rewriting it would change the file the R1 runs start from",
}
# Compressed logs too large to read in the test (about a gigabyte): every column of a weights recording is a
# number or a task name (tar_rl.runs.WEIGHTS_COLUMNS), so it names no path.
UNREAD = re.compile(r"(^|/)weights\.csv\.gz$")


def _text_of(path: Path) -> str | None:
    """The text a check reads in ``path``: a plain-text file's, a gzip file's contents, or a binary file's bytes
    (a checkpoint's stored strings); None for the :data:`UNREAD` logs."""
    data = path.read_bytes()
    if path.suffix == ".gz":
        if UNREAD.search(path.as_posix()):
            return None
        data = gzip.decompress(data)
    return data.decode(errors="replace")


def test_no_tracked_file_names_a_path_outside_the_repository():
    found = []
    files = {path.relative_to(REPO).as_posix(): path for path in tracked_files() if path.is_file()}
    assert not set(MACHINE_PATH_KEPT) - set(files), "MACHINE_PATH_KEPT lists files that are not tracked"
    for rel, path in files.items():
        text = None if rel in MACHINE_PATH_KEPT else _text_of(path)
        if text is None or not OUTSIDE.search(text):
            continue
        for number, line in enumerate(text.splitlines(), 1):
            if OUTSIDE.search(line):
                found.append(f"{rel}:{number}: {line.strip()[:120]}")
    assert not found, "paths outside the repository:\n" + "\n".join(found)


def test_examples_are_found():
    """The README's training loop and the command lines are seen by the tests above (a changed fence or marker
    convention would otherwise leave them unchecked)."""
    assert any(b.page.name == "README.md" and "TARLoss(" in b.code for b in PYTHON)
    assert any(args[:1] == ["train"] for _, args in COMMANDS)
    assert any(args[:1] == ["data"] for _, args in COMMANDS)
