"""MetaWorld v3 tasks: names, the one task ordering, difficulty groups, instructions, variations.

Task index. ``TASKS`` lists the 50 MetaWorld v3 task names in alphabetical order; a task's
index in it (``task_index``) is the task id used everywhere in tar-rl (datasets, one-hot
conditioning, evaluation tables). It does not depend on the installed MetaWorld version.

Groups. ``easy``/``medium``/``hard``/``very_hard`` are the difficulty groups the TAR paper uses
(28/11/6/5 tasks); ``mt10`` is MetaWorld's MT10 set; ``mt50`` all 50 tasks.

Variations. A MetaWorld task variation (object and goal placement) is fixed by the seed given to
``metaworld.MT1(task, seed=s)``, which samples 50 of them; ``reset(seed=...)`` is ignored by the
Sawyer environments. tar-rl numbers the variations of a task from a base seed: episode ``j``
uses variation ``j % 50`` of ``MT1(task, seed=base + j // 50)``, so a base seed and an episode
count name exactly which seeds are used (``variation_seeds``). Demonstrations and evaluation
draw from disjoint seed sets (``check_disjoint``).
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Sequence

from tar_rl.objectives.registry import did_you_mean

__all__ = [
    "DIFFICULTY_GROUPS",
    "GROUPS",
    "INSTRUCTIONS",
    "TASKS",
    "VARIATIONS_PER_SEED",
    "add_variations",
    "cached_variations",
    "check_disjoint",
    "expert",
    "group_of",
    "make_env",
    "resolve_tasks",
    "task_index",
    "variation",
    "variation_seeds",
    "variations_of",
]

VARIATIONS_PER_SEED = 50  # metaworld.MT1 samples 50 variations per seed

_EASY = (
    "button-press button-press-topdown button-press-topdown-wall button-press-wall coffee-button dial-turn "
    "door-close door-lock door-open door-unlock drawer-close drawer-open faucet-close faucet-open handle-press "
    "handle-press-side handle-pull handle-pull-side lever-pull plate-slide plate-slide-back plate-slide-back-side "
    "plate-slide-side reach reach-wall window-close window-open peg-unplug-side"
)
_MEDIUM = (
    "basketball bin-picking box-close coffee-pull coffee-push hammer peg-insert-side push-wall soccer sweep sweep-into"
)
_HARD = "assembly hand-insert pick-out-of-hole pick-place push push-back"
_VERY_HARD = "shelf-place disassemble stick-pull stick-push pick-place-wall"
_MT10 = (
    "reach push pick-place door-open drawer-open drawer-close button-press-topdown peg-insert-side "
    "window-open window-close"
)


def _v3(names: str) -> tuple[str, ...]:
    return tuple(f"{n}-v3" for n in names.split())


GROUPS: dict[str, tuple[str, ...]] = {
    "easy": _v3(_EASY),
    "medium": _v3(_MEDIUM),
    "hard": _v3(_HARD),
    "very_hard": _v3(_VERY_HARD),
    "mt10": _v3(_MT10),
}
TASKS: tuple[str, ...] = tuple(sorted(GROUPS["easy"] + GROUPS["medium"] + GROUPS["hard"] + GROUPS["very_hard"]))
GROUPS["mt50"] = TASKS
DIFFICULTY_GROUPS: tuple[str, ...] = ("easy", "medium", "hard", "very_hard")

#: One instruction per task, written for tar-rl (MetaWorld ships none). push-v3 and push-back-v3
#: get different texts so that text conditioning can tell them apart.
INSTRUCTIONS: dict[str, str] = {
    "assembly-v3": "Pick up the nut and place it onto the peg.",
    "basketball-v3": "Pick up the ball and dunk it into the basket.",
    "bin-picking-v3": "Grasp the puck in one bin and move it into the other bin.",
    "box-close-v3": "Grasp the lid and place it on the box to close it.",
    "button-press-topdown-v3": "Press the button from the top.",
    "button-press-topdown-wall-v3": "Press the button from the top, reaching past the wall.",
    "button-press-v3": "Press the button from the front.",
    "button-press-wall-v3": "Press the button from the front, reaching past the wall.",
    "coffee-button-v3": "Push the button on the coffee machine.",
    "coffee-pull-v3": "Pull the mug away from the coffee machine.",
    "coffee-push-v3": "Push the mug under the coffee machine.",
    "dial-turn-v3": "Rotate the dial by about 180 degrees.",
    "disassemble-v3": "Pick the nut off the peg.",
    "door-close-v3": "Close the door by pushing it shut.",
    "door-lock-v3": "Turn the door lock down to lock it.",
    "door-open-v3": "Open the door by pulling its handle.",
    "door-unlock-v3": "Turn the door lock up to unlock it.",
    "drawer-close-v3": "Push the drawer closed.",
    "drawer-open-v3": "Pull the drawer open.",
    "faucet-close-v3": "Rotate the faucet handle to close it.",
    "faucet-open-v3": "Rotate the faucet handle to open it.",
    "hammer-v3": "Pick up the hammer and hammer the nail into the wall.",
    "hand-insert-v3": "Move the hand into the hole in the table.",
    "handle-press-side-v3": "Press the handle down from the side.",
    "handle-press-v3": "Press the handle down.",
    "handle-pull-side-v3": "Pull the handle up from the side.",
    "handle-pull-v3": "Pull the handle up.",
    "lever-pull-v3": "Pull the lever up.",
    "peg-insert-side-v3": "Pick up the peg and insert it sideways into the hole.",
    "peg-unplug-side-v3": "Pull the peg out of the hole sideways.",
    "pick-out-of-hole-v3": "Pick the peg out of the hole and lift it to the goal.",
    "pick-place-v3": "Pick up the puck and place it at the goal.",
    "pick-place-wall-v3": "Pick up the puck and place it at the goal behind the wall.",
    "plate-slide-back-side-v3": "Slide the plate sideways back into the cabinet.",
    "plate-slide-back-v3": "Slide the plate back into the cabinet.",
    "plate-slide-side-v3": "Slide the plate sideways out of the cabinet to the goal.",
    "plate-slide-v3": "Slide the plate out of the cabinet to the goal.",
    "push-back-v3": "Push the puck backwards to the goal.",
    "push-v3": "Push the puck forward to the goal.",
    "push-wall-v3": "Push the puck to the goal around the wall.",
    "reach-v3": "Reach the goal position with the gripper.",
    "reach-wall-v3": "Reach the goal position past the wall.",
    "shelf-place-v3": "Pick up the puck and place it on the shelf.",
    "soccer-v3": "Push the ball into the goal.",
    "stick-pull-v3": "Grasp the stick and use it to pull the container to the goal.",
    "stick-push-v3": "Grasp the stick and use it to push the container to the goal.",
    "sweep-into-v3": "Sweep the puck into the hole.",
    "sweep-v3": "Sweep the puck off the table.",
    "window-close-v3": "Push the window closed.",
    "window-open-v3": "Push the window open.",
}

_INDEX = {name: i for i, name in enumerate(TASKS)}
_GROUP_OF = {name: group for group in DIFFICULTY_GROUPS for name in GROUPS[group]}


def _normalise(name: str) -> str:
    name = name.strip()
    return name if name.endswith("-v3") or name in GROUPS else f"{name}-v3"


def resolve_tasks(spec: str | Iterable[str]) -> tuple[str, ...]:
    """Task names from a group name, a task name or a mix of them, in ``TASKS`` order.

    Accepts ``"mt10"``, ``"hard"``, ``"pick-place"``, ``"pick-place-v3"``, a comma-separated
    string of these, or a list of them. Duplicates are dropped.

    Raises:
        ValueError: naming the unknown entries and listing the valid groups and tasks.
    """
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    chosen: set[str] = set()
    unknown = []
    for item in items:
        if not isinstance(item, str) or not item.strip():
            unknown.append(item)
            continue
        name = _normalise(item)
        if name in GROUPS:
            chosen.update(GROUPS[name])
        elif name in _INDEX:
            chosen.add(name)
        else:
            unknown.append(item)
    if unknown or not chosen:
        names = [*GROUPS, *(t[:-3] for t in TASKS)]
        hints = "".join(did_you_mean(str(item).strip(), names) for item in unknown)
        raise ValueError(
            f"unknown MetaWorld task or group {unknown or items!r}{hints}. Groups: {', '.join(GROUPS)}. "
            f"Tasks (the -v3 suffix is optional): {', '.join(t[:-3] for t in TASKS)}."
        )
    return tuple(sorted(chosen, key=_INDEX.__getitem__))


def task_index(name: str) -> int:
    """The task's fixed id: its position in ``TASKS`` (alphabetical order of the v3 names)."""
    if _normalise(name) not in _INDEX:
        raise ValueError(
            f"{name!r} is not a MetaWorld task name. Tasks (the -v3 suffix is optional): "
            f"{', '.join(t[:-3] for t in TASKS)}."
        )
    return _INDEX[_normalise(name)]


def group_of(name: str) -> str:
    """The paper's difficulty group of a task: ``easy``, ``medium``, ``hard`` or ``very_hard``."""
    return _GROUP_OF[TASKS[task_index(name)]]


def variation_seeds(base: int, n_episodes: int) -> tuple[int, ...]:
    """The MT1 seeds that ``n_episodes`` episodes numbered from seed ``base`` use."""
    if n_episodes <= 0:
        return ()
    return tuple(range(base, base + (n_episodes - 1) // VARIATIONS_PER_SEED + 1))


def check_disjoint(demo_seeds: Sequence[int], eval_seeds: Sequence[int]) -> None:
    """Refuse evaluation variations drawn from a seed that also produced demonstrations."""
    shared = sorted(set(demo_seeds) & set(eval_seeds))
    if shared:
        raise ValueError(
            f"evaluation seeds {shared} were also used for demonstrations: choose an evaluation seed "
            "outside the dataset's seeds (recorded in its metadata as 'variation_seeds')."
        )


@functools.lru_cache(maxsize=256)
def _benchmark(task: str, seed: int):
    import metaworld

    return metaworld.MT1(task, seed=seed)


# The variations of each (task, seed) this process has, built here (``_benchmark``) or received
# from another process (``add_variations``): evaluation workers get them from the parent instead
# of rebuilding ``MT1`` (about a second per task and seed).
_VARIATIONS: dict[tuple[str, int], tuple] = {}


def variation(task: str, base: int, episode: int):
    """The ``metaworld.Task`` (variation) that episode ``episode`` of ``task`` uses from seed ``base``.

    ``MT1`` objects are cached per (task, seed): building one takes about a second.
    """
    if episode < 0:
        raise ValueError(f"episode numbers start at 0, got {episode}.")
    seed = base + episode // VARIATIONS_PER_SEED
    return variations_of(task, seed)[episode % VARIATIONS_PER_SEED]


def variations_of(task: str, seed: int) -> tuple:
    """The 50 variations of ``metaworld.MT1(task, seed=seed)`` (cached per process)."""
    key = (task, seed)
    if key not in _VARIATIONS:
        _VARIATIONS[key] = tuple(_benchmark(task, seed).train_tasks)
    return _VARIATIONS[key]


def cached_variations(keys: Iterable[tuple[str, int]]) -> dict[tuple[str, int], tuple]:
    """The variations this process already holds for the given ``(task, seed)`` pairs (others left out)."""
    return {key: _VARIATIONS[key] for key in keys if key in _VARIATIONS}


def add_variations(found: dict[tuple[str, int], tuple]) -> None:
    """Cache variations built by another process (``cached_variations`` there); kept ones win."""
    for key, value in found.items():
        if len(value) != VARIATIONS_PER_SEED:
            raise ValueError(f"variations of {key} must be {VARIATIONS_PER_SEED} tasks, got {len(value)}")
        _VARIATIONS.setdefault(key, tuple(value))


# Compiled MuJoCo models, one per (XML file, frame buffer size) in this process, kept as they were
# right after compilation. A second env of a task copies one (``mj_copyModel``, a few ms) instead
# of parsing and compiling the XML again (~0.15 s).
_COMPILED: dict[tuple, object] = {}


def _initialize_simulation(env):
    """``MujocoEnv._initialize_simulation`` for ``env``, compiling each XML once per process."""
    import copy

    import mujoco

    key = (env.fullpath, env.width, env.height)
    template = _COMPILED.get(key)
    if template is None:
        model, data = type(env)._initialize_simulation(env)  # the class's own: parse and compile
        _COMPILED[key] = copy.copy(model)  # before the env changes anything in its model
        return model, data
    model = copy.copy(template)
    return model, mujoco.MjData(model)


def make_env(task: str):
    """A bare MetaWorld v3 environment for ``task`` (a gymnasium ``Env``).

    Call ``env.set_task(variation(...))`` before ``reset``: the variation fixes the object and
    goal placement, and makes the goal visible in the observation (``obs[36:39]``). The first
    env of a task in a process compiles its MuJoCo model from XML; later ones get a copy of that
    compiled model (the same model, bit for bit, each env with its own).
    """
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    cls = ALL_V3_ENVIRONMENTS[task]
    env = cls.__new__(cls)
    # The instance attribute shadows the class method while __init__ builds the simulation.
    env._initialize_simulation = functools.partial(_initialize_simulation, env)
    try:
        env.__init__()
    finally:
        del env._initialize_simulation
    return env


def expert(task: str):
    """MetaWorld's scripted expert for ``task``; ``expert(task).get_action(obs)`` gives an UNCLIPPED action."""
    from metaworld.policies import ENV_POLICY_MAP

    return ENV_POLICY_MAP[task]()
