"""The generated parts of the documentation: ``python docs/generate.py`` writes them, ``--check`` compares.

What it generates, each from where the code or the results hold it:

* ``docs/config.md``: every config group and field of ``tar-rl train`` with its type, default, allowed values and
  one-line meaning, from the typed configs (``recipes/config.py``, each head's config dataclass: types, defaults,
  the ``Attributes:`` lines of their docstrings) and the registries (weightings, heads, suites, importers). The
  allowed values are what the job's checks (``tar_rl.recipes.validate.validate``) accept: each setting is given a
  value no check accepts, and the refusal's message names the choices or the range.
* ``docs/figures/*.png``: copies of the figures the pages embed, from the benchmark results that draw them
  (:data:`FIGURES`).
* the blocks between ``<!-- generated: NAME ... -->`` and ``<!-- end generated: NAME -->`` markers
  (:data:`BLOCKS`): in ``README.md`` the regime study's decision table in brief, from
  ``benchmarks/results/regimes/decision.csv``; in ``docs/experiments.md`` Table III extended with the baselines,
  from ``benchmarks/results/regimes/baselines/table.md``, and TAR's tuning in R3, from ``tuning.md`` and
  ``final.md`` under ``benchmarks/results/regimes/tuning/``; in ``docs/objective.md`` the two-draw table of the
  heads' per-step losses, from ``benchmarks/results/regimes/diagnosis/noise.md``.

``tests/test_docs.py`` fails when a committed file differs from what this command writes.
"""

from __future__ import annotations

import argparse
import ast
import copy
import csv
import dataclasses
import inspect
import re
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
CONFIG_PAGE = "docs/config.md"
REGIMES_CSV = "benchmarks/results/regimes/decision.csv"
BASELINES_TABLE = "benchmarks/results/regimes/baselines/table.md"
TUNING_TABLE = "benchmarks/results/regimes/tuning/tuning.md"
TUNING_FINAL = "benchmarks/results/regimes/tuning/final.md"
NOISE_TABLE = "benchmarks/results/regimes/diagnosis/noise.md"

#: The embedded figures: docs/figures/<name> <- the result file that a benchmark command draws.
FIGURES = {
    "fig3_success_vs_neps.png": "benchmarks/results/paper-cpu/table/fig3_success_vs_neps.png",
    "fig5_weights.png": "benchmarks/results/paper-cpu/critical_windows/fig5_weights.png",
    "fig3_regimes.png": "benchmarks/results/regimes/fig3_regimes.png",
    "fig_paired.png": "benchmarks/results/regimes/fig_paired.png",
    "r3_dims_time.png": "benchmarks/results/regimes/diagnosis/dims_time.png",
    "r3_scatter.png": "benchmarks/results/regimes/diagnosis/scatter.png",
}

# The typed config's sections, in the order of the page (``policy`` has one config dataclass per head).
SECTIONS = ("objective", "data", "eval", "optim", "logging", "diagnostics")
# Fields of TrainConfig that are Hydra's own nodes, not settings.
HYDRA_NODES = ("defaults", "hydra")
_PROBE = "\x00probe"


# -- Docstrings ----------------------------------------------------------------------------------


def attribute_lines(cls: type) -> dict[str, str]:
    """The ``Attributes:`` entries of ``cls``'s docstring and its bases' (a subclass's entry wins), each joined
    into one line. An entry ``a, b: text`` documents both fields."""
    lines: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        doc = inspect.getdoc(klass) if klass.__doc__ else None
        if not doc or "Attributes:" not in doc:
            continue
        entries: dict[str, list[str]] = {}
        current: list[str] | None = None
        for line in doc.split("Attributes:", 1)[1].splitlines()[1:]:
            if not line.strip():
                continue
            indent = len(line) - len(line.lstrip())
            if indent <= 0:
                break  # the next section
            match = re.match(r"\s{4}([a-z_][a-z0-9_, ]*):\s*(.*)$", line)
            if indent == 4 and match:
                current = [match.group(2)]
                for name in match.group(1).split(","):
                    entries[name.strip()] = current
            elif current is not None:
                current.append(line.strip())
        lines.update({name: " ".join(text).strip() for name, text in entries.items()})
    return lines


def first_sentence(text: str) -> str:
    """``text`` up to the end of its first sentence (a full stop outside brackets and code, before a capital)."""
    depth, code = 0, False
    for i, char in enumerate(text):
        if char == "`":
            code = not code
        elif not code and char in "([":
            depth += 1
        elif not code and char in ")]":
            depth = max(depth - 1, 0)
        elif char == "." and not code and depth == 0 and re.match(r"\s+[A-Z]", text[i + 1 :]):
            return text[: i + 1]
    return text


def markdown(text: str) -> str:
    """Docstring markup as Markdown: ``code`` as `code`, :role:`~a.b` as `b`, table bars escaped."""
    text = re.sub(r":[a-z]+:`~[\w.]*?(\w+)`", r"`\1`", text)
    text = re.sub(r":[a-z]+:`([^`]+)`", r"`\1`", text)
    return text.replace("``", "`").replace("|", "\\|")


def meaning(cls: type, name: str) -> str:
    """The one-line meaning of field ``name`` of ``cls``; a field without an ``Attributes:`` line is an error."""
    lines = attribute_lines(cls)
    if name not in lines:
        raise SystemExit(
            f"{cls.__module__}.{cls.__qualname__}.{name} has no line in the docstring's Attributes: section; "
            "document it there, then run python docs/generate.py"
        )
    return markdown(first_sentence(lines[name]))


# -- Allowed values: what the job's checks accept -----------------------------------------------


def _set(config: dict, key: str, value) -> dict:
    probe = copy.deepcopy(config)
    node = probe
    *path, last = key.split(".")
    for part in path:
        node = node[part]
    node[last] = value
    return probe


def _refusal(config: dict, key: str, value) -> str | None:
    """The message with which the job's checks refuse ``key=value`` when it names ``key``; None when accepted."""
    from tar_rl.recipes import ConfigError
    from tar_rl.recipes.validate import validate

    try:
        validate(_set(config, key, value))
    except (ConfigError, ValueError, TypeError) as err:
        message = str(err)
        return message if re.match(rf"{re.escape(key)}\b", message) else None
    return None


def _rule(message: str, key: str) -> str:
    """The allowed values a refusal names: its list of choices, or the rule after "must"."""
    choices = re.search(r"one of (\[[^\]]*\])", message)
    if choices:
        return ", ".join(f"`{c}`" for c in ast.literal_eval(choices.group(1)))
    use = re.search(r"; use (.+)$", message)
    if use:
        return markdown(use.group(1))
    must = re.match(rf"{re.escape(key)}(?:=\S+)?(?: is [^,]*? and)? must (?:be |lie )?(.+?),? got\b", message)
    if must:
        # A rule shared with another setting ("must be >= 1 and policy.x >= 0") keeps this setting's part.
        return markdown(re.split(r" and [a-z_]+\.[a-z_]+", must.group(1))[0].rstrip(" ,"))
    return ""


def allowed(config: dict, key: str, default) -> str:
    """The values of ``key`` the job's checks accept, from what they say when refusing one ("" when no value of
    the probed kind is refused: any value of the field's type)."""
    if isinstance(default, bool) or isinstance(default, (list, dict)):
        return ""
    # Only values no check can take for a size: a large one would build a network of that size.
    if isinstance(default, str) or key.endswith(".name"):
        value = _PROBE
    elif isinstance(default, float):
        value = -1e9
    else:  # an int or an optional int
        value = -(10**9)
    message = _refusal(config, key, value)
    return _rule(message, key) if message else ""


# -- The page -----------------------------------------------------------------------------------


def _type(annotation) -> str:
    text = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", str(annotation))
    return text.replace("|", "\\|")


def _value(value) -> str:
    """A value as it is written on the command line."""
    if value is None:
        return "`null`"
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    if isinstance(value, str):
        return f"`{value}`" if value else '`""`'
    if isinstance(value, list):
        return "`[" + ",".join(str(v) for v in value) + "]`"
    return f"`{value}`"


def _default(f: dataclasses.Field):
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def _table(cls: type, prefix: str, config: dict, skip: tuple[str, ...] = ()) -> list[str]:
    rows = ["| field | type | default | allowed | meaning |", "|---|---|---|---|---|"]
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        key = f"{prefix}{f.name}"
        default = _default(f)
        rows.append(
            f"| `{key}` | {_type(f.type)} | {_value(default)} | {allowed(config, key, default)} | "
            f"{meaning(cls, f.name)} |"
        )
    return rows


def _summary(obj) -> str:
    doc = inspect.getdoc(type(obj)) or ""
    return markdown(first_sentence(" ".join(doc.split("\n\n")[0].split())))


def config_page() -> str:
    """The text of ``docs/config.md``."""
    from tar_rl.collectors.suites import SUITES
    from tar_rl.importers import IMPORTERS
    from tar_rl.objectives import WEIGHTINGS
    from tar_rl.policies import POLICIES
    from tar_rl.recipes import config as cfgmod

    base = cfgmod.default_config("tar", "mlp")
    out = [
        "# Configuration reference",
        "",
        "<!-- Generated by `python docs/generate.py` from the typed configs and the registries: do not edit. -->",
        "",
        "Every setting of `tar-rl train`, generated by `python docs/generate.py` from the typed configs",
        "(`recipes/config.py` and each head's config dataclass) and the registries; `tests/test_docs.py` fails when",
        "this page differs from what the command writes. Set a field on the command line as `section.field=value`",
        "(`tar-rl train optim.steps=50000 objective.gamma=2`), choose an option of a group as `group=option`",
        "(`tar-rl train objective=uniform policy=act data=mt10`); `tar-rl train --cfg job ...` prints the resolved",
        "config without running. An unknown key, a value of the wrong type or a value outside *allowed* stops the",
        "command before any work, naming the key. *Allowed* is what the job's checks accept (empty: any value of",
        "the type); training and the run folder are described in [training.md](training.md).",
        "",
        "## Groups and presets",
        "",
        "| group | options (default first) |",
        "|---|---|",
        "| `objective` | "
        + ", ".join(f"`{n}`" for n in _default_first(WEIGHTINGS, "tar"))
        + " (the weightings below); presets: "
        + ", ".join(
            f"`{n}` ({_changes(cfgmod.objective_config(p.name)(name=p.name), p)})"
            for n, p in cfgmod.OBJECTIVE_PRESETS.items()
        )
        + " |",
        "| `policy` | " + ", ".join(f"`{n}`" for n in _default_first(POLICIES, "mlp")) + " (the heads below) |",
    ]
    for group, options in cfgmod.PRESETS.items():
        cells = []
        for name, node in options.items():
            changed = _changes(options["default"], node)
            cells.append(f"`{name}`" + (f" ({changed})" if changed else ""))
        out.append(f"| `{group}` | {', '.join(cells)} |")
    out += ["", "A preset sets a section's fields; override them as usual (`data=mt50 data.n_demos=25`)."]

    out += ["", "## Top level", ""]
    out += _table(cfgmod.TrainConfig, "", base, skip=(*HYDRA_NODES, *SECTIONS, "policy", "init"))
    init_line = meaning(cfgmod.TrainConfig, "init")
    out.append(f"| `init.from` | str \\| None | `null` |  | {init_line} |")

    for section in SECTIONS:
        cls = cfgmod.ObjectiveConfig if section == "objective" else cfgmod.SECTIONS[section]
        doc = _summary_of_class(cls)
        out += ["", f"## `{section}`", "", doc, ""]
        out += _table(cls, f"{section}.", base)
        if section == "objective":
            out += _weighting_tables(cfgmod, WEIGHTINGS)

    out += [
        "",
        "## `policy`",
        "",
        "One option per registered head (`policy=<name>`, registry `tar_rl.policies.POLICIES`):",
        "",
    ]
    out += ["| name | what it is |", "|---|---|"]
    out += [f"| `{name}` | {markdown(spec.description)} |" for name, spec in POLICIES.items()]
    for name, spec in POLICIES.items():
        config = cfgmod.default_config("tar", name)
        out += ["", f"### `policy={name}` (`{spec.config.__name__}`)", ""]
        out += _table(spec.config, "policy.", config)

    out += ["", "## Suites (`data.suite=<name>`, registry `tar_rl.collectors.suites.SUITES`)", ""]
    out += ["| name | what it is | collects demonstrations | image observations |", "|---|---|---|---|"]
    for name, suite in SUITES.items():
        out.append(f"| `{name}` | {_summary(suite)} | {_yes(suite.collects)} | {_yes(suite.images)} |")

    out += ["", "## Importers (`tar-rl data import <name>`, registry `tar_rl.importers.IMPORTERS`)", ""]
    out += ["| name | what it imports |", "|---|---|"]
    out += [f"| `{name}` | {markdown(imp.help)} |" for name, imp in IMPORTERS.items()]
    return "\n".join(out) + "\n"


def _weighting_tables(cfgmod, weightings) -> list[str]:
    """The weightings, then one table per parameters class: the settings ``objective=<name>`` adds."""
    out = ["", "### Weightings (`objective=<name>`, registry `tar_rl.WEIGHTINGS`)", ""]
    out += ["| name | parameters | what it is |", "|---|---|---|"]
    out += [f"| `{name}` | `{w.params.__name__}` | {markdown(w.summary)} |" for name, w in weightings.items()]
    common = {f.name for f in dataclasses.fields(cfgmod.ObjectiveConfig)}
    owners: dict[type, list[str]] = {}
    for name, w in weightings.items():
        owners.setdefault(w.params, []).append(name)
    for params, names in owners.items():
        if not dataclasses.fields(params):
            continue
        options = ", ".join(f"`objective={n}`" for n in names)
        out += ["", f"#### {options} (`{params.__name__}`)", ""]
        config = cfgmod.default_config(names[0], "mlp")
        out += _table(cfgmod.objective_config(names[0]), "objective.", config, skip=tuple(common))
    return out


def _default_first(registry, default: str) -> list[str]:
    return [default, *(n for n in registry if n != default)]


def _changes(default, node) -> str:
    return ", ".join(
        f"{f.name}={_value(getattr(node, f.name)).strip('`')}"
        for f in dataclasses.fields(node)
        if getattr(node, f.name) != getattr(default, f.name)
    )


def _summary_of_class(cls: type) -> str:
    doc = inspect.getdoc(cls) or ""
    return markdown(" ".join(doc.split("\n\n")[0].split()))


def _yes(flag: bool) -> str:
    return "yes" if flag else "no"


# -- Generated blocks of the pages ---------------------------------------------------------------


def _num(text: str, digits: int, signed: bool = False) -> str:
    if text == "":
        return "-"
    return f"{float(text):+.{digits}f}" if signed else f"{float(text):.{digits}f}"


def _p(text: str) -> str:
    """A p-value: three decimals, ``<0.001`` below that, ``-`` where there is none."""
    return "-" if text in ("", "nan") else "<0.001" if float(text) < 0.001 else f"{float(text):.3f}"


def regimes_block() -> str:
    """The regime study's decision table in brief, from ``decision.csv``."""
    with open(REPO / REGIMES_CSV, newline="") as f:
        rows = list(csv.DictReader(f))
    out = [
        "| regime | pairs | passes | success % uniform / TAR | Δ success [95% CI] | Holm p | MDE (80%) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ci = f"[{_num(r['d_success_ci_low'], 2, True)}, {_num(r['d_success_ci_high'], 2, True)}]"
        out.append(
            f"| {r['regime']} | {r['pairs']} | {_num(r['passes_uniform'], 0)} | {_num(r['success_uniform'], 1)} / "
            f"{_num(r['success_tar'], 1)} | {_num(r['d_success'], 2, True)} {ci} | {_p(r['holm_p'])} | "
            f"{_num(r['mde_success'], 1)} |"
        )
    return "\n".join(out)


def _untitled(path: str) -> str:
    """A markdown table file written by a benchmark command, without its title line."""
    lines = (REPO / path).read_text().strip().splitlines()
    return "\n".join(lines[1:] if lines[0].startswith("# ") else lines).strip()


def baselines_block() -> str:
    """Table III extended with the baselines, as ``python -m benchmarks.studies baselines table`` writes it."""
    return _untitled(BASELINES_TABLE)


def tuning_block() -> str:
    """TAR's tuning in R3 on the tuning seed and, once its final runs finished, the final comparison, as
    ``python -m benchmarks.studies tuning table`` writes them."""
    final = REPO / TUNING_FINAL
    return _untitled(TUNING_TABLE) + (f"\n\n{_untitled(TUNING_FINAL)}" if final.is_file() else "")


def noise_block() -> str:
    """Two draws of the chunked heads' per-step losses: the per-head table and the explanation of ``noise.md`` as
    ``python -m benchmarks.analysis noise`` writes it (its per-run table stays in the file)."""
    heads, *_, about = _untitled(NOISE_TABLE).split("\n\n")
    return f"{heads}\n\n{about}"


#: The generated blocks: (page, block name) -> the function that writes the block's content.
BLOCKS = {
    ("README.md", "regimes"): regimes_block,
    ("docs/experiments.md", "baselines"): baselines_block,
    ("docs/experiments.md", "tuning"): tuning_block,
    ("docs/objective.md", "noise"): noise_block,
}


def begin_marker(name: str) -> str:
    return f"<!-- generated: {name} (python docs/generate.py) -->"


def end_marker(name: str) -> str:
    return f"<!-- end generated: {name} -->"


def page_with_blocks(page: str) -> str:
    """``page`` with each of its generated blocks as the command writes it (a blank line inside each marker)."""
    text = (REPO / page).read_text()
    for (where, name), block in BLOCKS.items():
        if where != page:
            continue
        begin, end = text.find(begin_marker(name)), text.find(end_marker(name))
        if begin < 0 or end < begin:
            raise SystemExit(f"{page} lacks the markers {begin_marker(name)!r} ... {end_marker(name)!r}")
        text = (
            text[:begin]
            + f"{begin_marker(name)}\n\n{block()}\n\n{end_marker(name)}"
            + text[end + len(end_marker(name)) :]
        )
    return text


# -- The command --------------------------------------------------------------------------------


def outputs() -> dict[str, bytes]:
    """Every generated file, by its path relative to the repository, with the content the command writes."""
    files = {CONFIG_PAGE: config_page().encode()}
    for page in dict.fromkeys(page for page, _ in BLOCKS):
        files[page] = page_with_blocks(page).encode()
    for name, source in FIGURES.items():
        files[f"docs/figures/{name}"] = (REPO / source).read_bytes()
    return files


def stale() -> list[str]:
    """The generated files whose committed content differs from what the command writes."""
    return [
        path
        for path, content in outputs().items()
        if not (REPO / path).is_file() or (REPO / path).read_bytes() != content
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="write nothing; exit 1 naming the files that differ")
    args = parser.parse_args(argv)
    if args.check:
        differ = stale()
        for path in differ:
            print(f"{path} differs from what python docs/generate.py writes")
        return 1 if differ else 0
    for path, content in outputs().items():
        target = REPO / path
        target.parent.mkdir(parents=True, exist_ok=True)
        if not target.is_file() or target.read_bytes() != content:
            target.write_bytes(content)
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
