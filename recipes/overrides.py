"""The command line of ``tar-rl train`` checked before Hydra composes it: one line per problem, with a suggestion.

Hydra refuses an unknown key, a value of the wrong type or an unknown group option with a report of several
lines (its search path, the node's types). :func:`check_overrides` finds the same problems first and names each
as ``<field>: <problem>``, with the closest valid name for a mistyped key or option (``objective=tarr``: did you
mean 'tar'?). What it accepts, Hydra then composes as usual; ``hydra.*`` settings are Hydra's own and left to it.
"""

from __future__ import annotations

import dataclasses
import difflib
import re

from tar_rl.objectives import WEIGHTINGS
from tar_rl.objectives.registry import did_you_mean
from tar_rl.policies import POLICIES

from .config import (
    CONFIG_NAME,
    OBJECTIVE_PRESETS,
    PRESETS,
    SECTIONS,
    TrainConfig,
    int_rule,
    objective_config,
    register_configs,
    setting_bounds,
)
from .errors import ConfigError

__all__ = ["check_overrides"]

# What OmegaConf calls the types it fails to convert a value to.
_KINDS = {"Integer": "an integer", "Float": "a number", "Boolean": "a boolean (true or false)", "String": "a string"}


def _groups() -> dict[str, list[str]]:
    """Each config group and its options (``group=option`` on the command line)."""
    return {
        "objective": [*WEIGHTINGS, *OBJECTIVE_PRESETS],
        "policy": list(POLICIES),
        **{group: list(options) for group, options in PRESETS.items()},
    }


def _fields(cls) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


def _head_settings(head: str) -> set[str]:
    return {f"policy.{name}" for name in _fields(POLICIES.get(head).config)}


def _objective_settings(option: str) -> set[str]:
    """The settings of the ``objective`` option ``option`` (a weighting, or a preset of one)."""
    node = OBJECTIVE_PRESETS.get(option)
    return {f"objective.{name}" for name in _fields(type(node) if node is not None else objective_config(option))}


def _settings() -> set[str]:
    """Every setting's dotted name but the policy head's and the weighting's (Hydra's ``defaults`` and ``hydra``
    nodes left out)."""
    scalars = _fields(TrainConfig) - {*SECTIONS, "objective", "policy", "init", "defaults", "hydra"}
    sections = {f"{section}.{name}" for section, cls in SECTIONS.items() for name in _fields(cls)}
    return scalars | sections | {"init.from"}


def _suggest(key: str, names: set[str]) -> str:
    """The closest setting to ``key`` (`` (did you mean 'x'?)``): by its whole name, else by its last part
    (``lr`` -> ``optim.lr``); ``""`` when none is close."""
    hint = did_you_mean(key, names)
    if hint:
        return hint
    tails = {name.rsplit(".", 1)[-1]: name for name in sorted(names)}
    close = difflib.get_close_matches(key.rsplit(".", 1)[-1], list(tails), n=1, cutoff=0.8)
    return f" (did you mean {tails[close[0]]!r}?)" if close else ""


def _check_key(key: str, heads: list[str], objectives: list[str]) -> None:
    """Refuse a key that names no setting; a head's setting must be one of every head chosen (``heads``), a
    weighting's one of every objective chosen (``objectives``)."""
    parts = key.split(".")
    name = ".".join(parts[:2])  # a setting's value may be a list or a dict: what lies below it is Hydra's to check
    if parts[0] == "policy" and len(parts) > 1:
        for head in heads:
            known = _head_settings(head)
            if name not in known:
                raise ConfigError(f"{key}: the head {head!r} has no such setting{_suggest(name, known)}")
        return
    if parts[0] == "objective" and len(parts) > 1:
        for option in objectives:
            known = _objective_settings(option)
            if name not in known:
                owners = [w for w in WEIGHTINGS if name in _objective_settings(w)]
                hint = f"; it is a setting of objective={'|'.join(owners)}" if owners else _suggest(name, known)
                raise ConfigError(f"{key}: objective={option} has no such setting{hint}")
        return
    if name not in _settings():
        known = _settings() | set(_groups()) | {name for head in heads for name in _head_settings(head)}
        known |= {name for option in objectives for name in _objective_settings(option)}
        raise ConfigError(f"{key}: no such setting{_suggest(key, known)}")


def _problem(key: str, message: str) -> str:
    """``<key>: <problem>`` from OmegaConf's message for a value it refuses (``seed: 'abc' is not an integer``)."""
    first = message.strip().splitlines()[0]
    converted = re.match(r"Value '(.*)' of type '\w+' could not be converted to (\w+)", first)
    boolean = re.match(r"Value '(.*)' is not a valid bool", first)
    if converted:
        problem = f"{converted.group(1)!r} is not {_KINDS.get(converted.group(2), converted.group(2))}"
    elif boolean:
        problem = f"{boolean.group(1)!r} is not {_KINDS['Boolean']}"
    else:
        problem = first
    bounds = setting_bounds(key)
    if bounds is not None and problem.endswith("is not an integer"):
        problem += f"; {key} must be {int_rule(*bounds)}"
    return f"{key}: {problem}"


def _compose(overrides: list[str]) -> None:
    """Compose the config as ``tar-rl train`` does; what Hydra refuses becomes a :class:`ConfigError` of one line."""
    from hydra import compose, initialize
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    try:
        with initialize(version_base="1.3", config_path=None):
            compose(config_name=CONFIG_NAME, overrides=overrides)
    except (HydraException, OmegaConfBaseException) as err:
        cause = err.__cause__ if isinstance(err.__cause__, OmegaConfBaseException) else err
        key = getattr(cause, "full_key", None)
        text = (getattr(cause, "msg", None) or str(err)).strip() or type(err).__name__
        if key:  # a list's item (policy.hidden[0]) is reported as its setting
            raise ConfigError(_problem(re.sub(r"\[\d+\]$", "", key), text)) from None
        raise ConfigError(text.splitlines()[0]) from None


def check_overrides(argv: list[str]) -> None:
    """Check the arguments of ``tar-rl train`` (Hydra's flags and overrides) before Hydra runs them.

    Every value of a ``-m`` sweep is checked, each with the first value of every other sweep.

    Raises:
        ConfigError: ``<field>: <problem>`` on one line: an unknown setting, group or option (with the closest
            valid name), a value of the wrong type, or several values without ``-m``.
    """
    from hydra._internal.utils import get_args_parser
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import HydraException

    args = get_args_parser().parse_args(argv)
    if args.shell_completion:
        return
    register_configs()
    try:
        parsed = OverridesParser.create().parse_overrides(args.overrides)
    except HydraException as err:
        raise ConfigError(str(err).strip().splitlines()[0]) from None
    parsed = [o for o in parsed if not (o.key_or_group == "hydra" or o.key_or_group.startswith(("hydra.", "hydra/")))]
    groups = _groups()
    lines: list[list[str]] = []  # per override, the overrides it stands for: a sweep's one per value
    values: list[list[str] | None] = []  # per override, its values; None: a value Hydra alone reads
    for override in parsed:
        if override.is_sweep_override():
            if not args.multirun:
                raise ConfigError(
                    f"{override.input_line}: several values run only as a sweep (add -m); a list is [a,b]"
                )
            try:
                sweep = list(override.sweep_string_iterator())
            except HydraException:  # an interval, for a sweeper that samples it
                sweep = None
            values.append(sweep)
            lines.append(
                [override.input_line] if sweep is None else [f"{override.get_key_element()}={v}" for v in sweep]
            )
        else:
            values.append([str(override.value())])
            lines.append([override.input_line])
    heads, objectives = ["mlp"], ["tar"]  # the default head and weighting
    for override, vals in zip(parsed, values):
        key = override.key_or_group
        if key in groups and vals is not None:
            for value in vals:
                if value not in groups[key]:
                    options = groups[key]
                    hint = did_you_mean(value, options)
                    raise ConfigError(f"{key}: no option {value!r}{hint}; options: {', '.join(options)}")
            if key == "policy":
                heads = vals
            if key == "objective":
                objectives = vals
    for override in parsed:
        if override.key_or_group not in groups:
            _check_key(override.key_or_group, heads, objectives)
    first = [options[0] for options in lines]
    _compose(first)
    for i, options in enumerate(lines):
        for other in options[1:]:
            _compose([*first[:i], other, *first[i + 1 :]])
