"""What the studies' plans fix once for all of them: the arms a comparison pairs (and the arm a run's config is) and
the task lists they train on.

Every study and analysis reads these names from here, so that a comparison's baseline is one name everywhere (the
report's :data:`tar_rl.report.BASELINE`, against which its paired tables are computed).
"""

from __future__ import annotations

from benchmarks.studies.core import Arm
from tar_rl.report.stats import BASELINE

__all__ = ["BASELINE", "CHUNKED_ARMS", "EIGHT_TASKS", "PAIR", "SOURCE_TASKS", "TREATMENT", "arm_of"]

#: The treatment every paired comparison puts beside :data:`BASELINE` (``uniform``): TAR at tar-rl's defaults.
TREATMENT = "tar"
#: The two arms of a paired stage: uniform and TAR.
PAIR = (Arm.objective(BASELINE), Arm.objective(TREATMENT))
#: The chunked-heads regimes' arms (objective options): uniform, TAR at tar-rl's defaults, the gentle preset. Their
#: four TAR-vs-uniform comparisons (R4, R5 x tar, tar_gentle) are a second Holm family.
CHUNKED_ARMS = (BASELINE, TREATMENT, "tar_gentle")
#: The eight tasks of the recipe's default job: two per difficulty group.
EIGHT_TASKS = (
    "[reach,button-press-topdown,basketball,peg-insert-side,assembly,pick-out-of-hole,stick-pull,pick-place-wall]"
)
#: MT50 without the default eight tasks, in MetaWorld's alphabetical order: R1's pretraining tasks.
SOURCE_TASKS = (
    "bin-picking,box-close,button-press-topdown-wall,button-press,button-press-wall,coffee-button,coffee-pull,"
    "coffee-push,dial-turn,disassemble,door-close,door-lock,door-open,door-unlock,drawer-close,drawer-open,"
    "faucet-close,faucet-open,hammer,hand-insert,handle-press-side,handle-press,handle-pull-side,handle-pull,"
    "lever-pull,peg-unplug-side,pick-place,plate-slide-back-side,plate-slide-back,plate-slide-side,plate-slide,"
    "push-back,push,push-wall,reach-wall,shelf-place,soccer,stick-push,sweep-into,sweep,window-close,window-open"
)


def arm_of(config: dict) -> str:
    """A run's arm from its config: the objective's name, ``tar_gentle`` for a ``tar`` run with the preset's gamma,
    cap and w_max (its ``objective.name`` is ``tar``)."""
    from tar_rl.recipes.config import OBJECTIVE_PRESETS

    objective = config.get("objective") or {}
    gentle = OBJECTIVE_PRESETS["tar_gentle"]
    keys = ("gamma", "cap", "w_max")
    if objective.get("name") == gentle.name and all(objective.get(k) == getattr(gentle, k) for k in keys):
        return "tar_gentle"
    return str(objective.get("name"))
