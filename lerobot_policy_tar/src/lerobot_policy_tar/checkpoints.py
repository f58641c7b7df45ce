"""Checkpoints between a TAR policy and its base policy: ``lerobot-tar to-base`` and ``lerobot-tar to-tar``.

A TAR policy's network, processors and inference are its base policy's; only its config (the type ``act_tar`` and
the ``tar`` settings), the schedule's count ``tar_step`` and, with ``policy.tar.signal=time_normalized``, the
running means ``tar_normalizer`` differ. So:

* :func:`to_base` writes a ``*_tar`` checkpoint as its base type (``act``, ``diffusion``, ...): the base config
  with every base field kept, the same weights without TAR's state, the same processors. Any LeRobot loads it and
  acts exactly as the TAR checkpoint does; a robot needs neither the plugin nor tar-rl.
* :func:`to_tar` writes a base checkpoint (a pretrained ``smolvla``, an ``act`` of your own) as its TAR type with
  the schedule at step 0, so that ``lerobot-train --policy.path=...`` post-trains it with TAR: LeRobot reads a
  policy's type from its checkpoint's ``config.json`` (``--policy.type`` beside ``--policy.path`` is ignored), so the
  type has to be in the checkpoint. ``--policy.tar.<name>=...`` sets TAR's settings on the command line as usual.

Both build the policy of the written type with LeRobot's factory, load the weights into it (every key checked) and
save it with LeRobot's ``save_pretrained``; the processors' files, which name no policy type, are copied as they
are (loading them would fetch a VLM's tokenizer). The new checkpoint is written in a temporary sibling folder and
renamed into place when complete; an existing folder is never replaced.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from dataclasses import fields
from pathlib import Path

from .configuration_tar import BASES, TARSettings

__all__ = ["TAR_TYPES", "CheckpointError", "checkpoint_folder", "checkpoint_type", "to_base", "to_tar"]

#: TAR type -> base type.
TAR_TYPES = {f"{base}_tar": base for base in BASES}
CONFIG_FILE = "config.json"
WEIGHTS_FILE = "model.safetensors"
#: The processors' files (``policy_preprocessor.json``, its steps' ``*.safetensors``, the postprocessor's).
PROCESSOR_PREFIXES = ("policy_preprocessor", "policy_postprocessor")


class CheckpointError(ValueError):
    """A checkpoint that cannot be converted as asked (not a policy checkpoint, of the wrong type, a folder in the
    way)."""


def checkpoint_folder(path: str | os.PathLike) -> Path:
    """The folder holding ``config.json`` and ``model.safetensors``: ``path`` itself or its ``pretrained_model``
    (LeRobot's ``checkpoints/<step>/`` holds one)."""
    path = Path(path)
    if not (path / CONFIG_FILE).is_file() and (path / "pretrained_model" / CONFIG_FILE).is_file():
        path = path / "pretrained_model"
    for name in (CONFIG_FILE, WEIGHTS_FILE):
        if not (path / name).is_file():
            raise CheckpointError(f"{path} is not a LeRobot policy checkpoint: it has no {name}")
    return path


def checkpoint_type(path: Path) -> str:
    """The policy type a checkpoint's ``config.json`` names (read as JSON, before anything is built)."""
    try:
        config = json.loads((path / CONFIG_FILE).read_text())
    except (OSError, UnicodeDecodeError, ValueError) as err:
        raise CheckpointError(f"{path / CONFIG_FILE} cannot be read: {type(err).__name__}: {err}") from None
    kind = config.get("type") if isinstance(config, dict) else None
    if not isinstance(kind, str):
        raise CheckpointError(f"{path / CONFIG_FILE} names no policy type")
    return kind


def _check_new(out: Path) -> None:
    if out.exists():
        raise CheckpointError(f"{out} exists: choose a new folder for the converted checkpoint")


def _convert(src: Path, out: Path, config) -> Path:
    """Build ``config``'s policy with LeRobot's factory, load ``src``'s weights into it, save it with ``src``'s
    processors at ``out`` (through a temporary sibling folder)."""
    from lerobot.policies.factory import get_policy_class
    from safetensors.torch import load_model

    policy = get_policy_class(config.type)(config)
    missing, unexpected = load_model(policy, str(src / WEIGHTS_FILE), strict=False)
    # a TAR checkpoint's count and running means per time bin (time_normalized), dropped for a base
    unexpected = [key for key in unexpected if key != "tar_step" and not key.startswith("tar_normalizer.")]
    if missing or unexpected:
        raise CheckpointError(
            f"{src / WEIGHTS_FILE} does not fit a {config.type!r} policy of its own config: missing "
            f"{sorted(missing)}, unexpected {sorted(unexpected)}"
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    try:
        policy.save_pretrained(tmp)
        for file in sorted(src.iterdir()):
            if file.is_file() and file.name.startswith(PROCESSOR_PREFIXES):
                shutil.copyfile(file, tmp / file.name)
        os.rename(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def _fields_of(config, config_class) -> dict:
    """The values of ``config_class``'s init fields, read from ``config``."""
    return {f.name: getattr(config, f.name) for f in fields(config_class) if f.init and hasattr(config, f.name)}


def to_base(src: str | os.PathLike, out: str | os.PathLike) -> Path:
    """Write the TAR checkpoint ``src`` as its base type at ``out`` (a new folder); ``out``.

    Raises:
        CheckpointError: ``src`` is not a policy checkpoint or not a TAR one (naming its type), or ``out`` exists.
    """
    from lerobot.configs.policies import PreTrainedConfig

    src, out = checkpoint_folder(src), Path(out)
    kind = checkpoint_type(src)
    if kind not in TAR_TYPES:
        raise CheckpointError(
            f"{src} is a {kind!r} checkpoint, not a TAR one ({', '.join(TAR_TYPES)}): any LeRobot runs it as it is"
        )
    _check_new(out)
    tar_config = PreTrainedConfig.from_pretrained(src)
    base_class = PreTrainedConfig.get_choice_class(TAR_TYPES[kind])
    return _convert(src, out, base_class(**_fields_of(tar_config, base_class)))


def to_tar(src: str | os.PathLike, out: str | os.PathLike, tar: TARSettings | None = None) -> Path:
    """Write the base checkpoint ``src`` (``act``, ``diffusion``, ``smolvla``, ``pi0``, ``pi05``) as its TAR type at
    ``out`` (a new folder), with TAR's settings ``tar`` (default: tar-rl's) and the schedule at step 0; ``out``.

    Raises:
        CheckpointError: ``src`` is not a policy checkpoint, is already a TAR one, or has a type without a TAR
            version (naming it); ``out`` exists.
        ValueError: a TAR setting out of range.
    """
    from lerobot.configs.policies import PreTrainedConfig

    from .configuration_tar import tar_config_class

    src, out = checkpoint_folder(src), Path(out)
    kind = checkpoint_type(src)
    if kind in TAR_TYPES:
        raise CheckpointError(f"{src} is already a TAR checkpoint ({kind!r}): pass it to --policy.path as it is")
    if kind not in BASES:
        raise CheckpointError(
            f"{src} is a {kind!r} checkpoint; TAR has versions of {', '.join(BASES)} only (docs/lerobot.md)"
        )
    _check_new(out)
    tar_class = tar_config_class(kind)
    tar = tar if tar is not None else next(f for f in fields(tar_class) if f.name == "tar").default_factory()
    tar.validate()
    base_config = PreTrainedConfig.from_pretrained(src)
    return _convert(src, out, tar_class(**_fields_of(base_config, tar_class), tar=tar))
