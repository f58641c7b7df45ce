"""The command line of ``tar-rl train`` as Hydra composes it, its errors in one line each, with a suggestion.

Hydra refuses an unknown key, a value of the wrong type or an unknown group option with a report of several
lines (its search path, the node's types). :func:`check_overrides` composes the command line as ``tar-rl train``
does and names each problem Hydra finds as ``<field>: <problem>``, with the closest valid name for a mistyped key or
option (``objective=tarr``: did you mean 'tar'?). ``hydra.*`` settings are Hydra's own and left to it.
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
    SECTIONS,
    TrainConfig,
    group_options,
    int_rule,
    objective_config,
    register_configs,
    setting_bounds,
)
from .errors import ConfigError

__all__ = ["check_overrides"]

# What OmegaConf calls the types it fails to convert a value to.
_KINDS = {"Integer": "an integer", "Float": "a number", "Boolean": "a boolean (true or false)", "String": "a string"}


def _settings(prefix: str, cls: type) -> set[str]:
    """The dotted names of the fields of the dataclass ``cls`` under ``prefix`` (``policy.``)."""
    return {prefix + f.name for f in dataclasses.fields(cls)}


def _head_settings(head: str) -> set[str]:
    return _settings("policy.", POLICIES.get(head).config)


def _objective_settings(option: str) -> set[str]:
    """The settings of the ``objective`` option ``option`` (a weighting, or a preset of one)."""
    node = OBJECTIVE_PRESETS.get(option)
    return _settings("objective.", type(node) if node is not None else objective_config(option))


def _job_settings() -> set[str]:
    """Every setting's dotted name but the policy head's and the weighting's (Hydra's ``defaults`` and ``hydra``
    nodes left out)."""
    scalars = _settings("", TrainConfig) - {*SECTIONS, "objective", "policy", "init", "defaults", "hydra"}
    return scalars.union({"init.from"}, *(_settings(f"{section}.", cls) for section, cls in SECTIONS.items()))


def _suggest(key: str, names: set[str]) -> str:
    """The closest setting to ``key`` (`` (did you mean 'x'?)``): by its whole name, else by its last part
    (``lr`` -> ``optim.lr``); ``""`` when none is close."""
    hint = did_you_mean(key, names)
    if hint:
        return hint
    tails = {name.rsplit(".", 1)[-1]: name for name in sorted(names)}
    close = difflib.get_close_matches(key.rsplit(".", 1)[-1], list(tails), n=1, cutoff=0.8)
    return f" (did you mean {tails[close[0]]!r}?)" if close else ""


def _key_problem(key: str, head: str, objective: str) -> str | None:
    """What is wrong with a key that names no setting of the head and the ``objective`` option it is composed with
    (None: it names one; what lies below a setting, a list's or a dict's item, is Hydra's to check)."""
    parts = key.split(".")
    name = ".".join(parts[:2])
    if parts[0] == "policy" and len(parts) > 1:
        known = _head_settings(head)
        return None if name in known else f"{key}: the head {head!r} has no such setting{_suggest(name, known)}"
    if parts[0] == "objective" and len(parts) > 1:
        known = _objective_settings(objective)
        if name in known:
            return None
        owners = [w for w in WEIGHTINGS if name in _objective_settings(w)]
        hint = f"; it is a setting of objective={'|'.join(owners)}" if owners else _suggest(name, known)
        return f"{key}: objective={objective} has no such setting{hint}"
    if name in _job_settings():
        return None
    known = _job_settings() | set(group_options()) | _head_settings(head) | _objective_settings(objective)
    return f"{key}: no such setting{_suggest(key, known)}"


def _chosen(overrides: list[str]) -> tuple[str, str]:
    """The head and the ``objective`` option a list of overrides composes (the defaults: ``mlp``, ``tar``)."""
    chosen = dict(o.split("=", 1) for o in overrides if o.split("=", 1)[0] in ("policy", "objective"))
    return chosen.get("policy", "mlp"), chosen.get("objective", "tar")


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
    from hydra.errors import HydraException, MissingConfigException
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError, OmegaConfBaseException

    try:
        with initialize(version_base="1.3", config_path=None):
            compose(config_name=CONFIG_NAME, overrides=overrides)
    except (HydraException, OmegaConfBaseException) as err:
        cause = err.__cause__ if isinstance(err.__cause__, OmegaConfBaseException) else err
        key = getattr(cause, "full_key", None)
        text = (getattr(cause, "msg", None) or str(err)).strip() or type(err).__name__
        missing = re.match(r"In '\w+': Could not find '(\w+)/(.*)'", text)
        if isinstance(err, MissingConfigException) and missing and missing.group(1) in group_options():
            group, value = missing.groups()
            options = list(group_options()[group])
            hint = did_you_mean(value, options)
            raise ConfigError(f"{group}: no option {value!r}{hint}; options: {', '.join(options)}") from None
        if isinstance(cause, (ConfigAttributeError, ConfigKeyError)) and key:
            # the override that names it (Hydra names the first part of it that is no setting)
            given = [o.split("=", 1)[0].lstrip("+~") for o in overrides]
            key = next((k for k in given if k == key or k.startswith(f"{key}.")), key)
            problem = _key_problem(key, *_chosen(overrides))
            if problem:
                raise ConfigError(problem) from None
        if key:  # a list's item (policy.hidden[0]) is reported as its setting
            raise ConfigError(_problem(re.sub(r"\[\d+\]$", "", key), text)) from None
        raise ConfigError(text.splitlines()[0]) from None


def check_overrides(argv: list[str]) -> None:
    """Check the arguments of ``tar-rl train`` (Hydra's flags and overrides) before Hydra runs them: compose them as
    it will, and name what it refuses.

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
    lines: list[list[str]] = []  # per override, the overrides it stands for: a sweep's one per value
    for override in parsed:
        if not override.is_sweep_override():
            lines.append([override.input_line])
            continue
        if not args.multirun:
            raise ConfigError(f"{override.input_line}: several values run only as a sweep (add -m); a list is [a,b]")
        try:
            lines.append([f"{override.get_key_element()}={v}" for v in override.sweep_string_iterator()])
        except HydraException:  # an interval, for a sweeper that samples it
            lines.append([override.input_line])
    first = [options[0] for options in lines]
    for override in parsed:  # Hydra adds a key no setting has (+key=value) to the config; tar-rl train has none
        added = override.is_add() or override.is_force_add()
        problem = _key_problem(override.key_or_group, *_chosen(first)) if added else None
        if problem and override.key_or_group not in group_options():
            raise ConfigError(problem)
    _compose(first)
    for i, options in enumerate(lines):
        for other in options[1:]:
            _compose([*first[:i], other, *first[i + 1 :]])
