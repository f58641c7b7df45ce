"""Synthetic run directories with hand-chosen rollouts, shared by the report and experiment tests, and the final
rollouts of a committed run read with pandas alone.

The run directories are written file by file, per the recipe's run-directory format; every expected
number is worked out by hand in the comments.
"""

from __future__ import annotations

import json

import pandas as pd
import yaml

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
H = 100  # horizon of the synthetic evaluations: rho = steps / 100

# Per run: task -> rollouts as (success, steps). Two tasks x 4 rollouts: K = ceil(0.2 * 4) = 1, so
# Fast20 of a task is its smallest rho. Groups: reach is "easy", assembly is "hard".
#
# uniform, seed 0: reach 2/4 = .50, Fast20 .2, sum rho .2+.4+1+1 = 2.6; assembly 1/4 = .25, Fast20 .5,
#   sum rho 3.5. Overall success (.5+.25)/2 = .375, Fast20 (.2+.5)/2 = .35, NEPS (2.6+3.5)/3 = 2.0333.
# uniform, seed 1: reach 3/4 = .75, Fast20 .1, sum 1.9; assembly 2/4 = .5, Fast20 .4, sum 3.0.
#   Overall .625, Fast20 .25, NEPS 4.9/5 = .98.
# tar, seed 0: reach 4/4 = 1, Fast20 .1, sum 1.0; assembly 2/4 = .5, Fast20 .3, sum 2.8.
#   Overall .75, Fast20 .2, NEPS 3.8/6 = .6333.
# tar, seed 1: reach 3/4 = .75, Fast20 .2, sum 1.6; assembly 3/4 = .75, Fast20 .3, sum 1.9.
#   Overall .75, Fast20 .25, NEPS 3.5/6 = .5833.
S, F = True, False
ROLLOUTS = {
    ("uniform", 0): {
        "reach": [(S, 20), (S, 40), (F, 100), (F, 100)],
        "assembly": [(S, 50), (F, 100), (F, 100), (F, 100)],
    },
    ("uniform", 1): {
        "reach": [(S, 10), (S, 30), (S, 50), (F, 100)],
        "assembly": [(S, 40), (S, 60), (F, 100), (F, 100)],
    },
    ("tar", 0): {"reach": [(S, 10), (S, 20), (S, 30), (S, 40)], "assembly": [(S, 30), (S, 50), (F, 100), (F, 100)]},
    ("tar", 1): {"reach": [(S, 20), (S, 20), (S, 20), (F, 100)], "assembly": [(S, 30), (S, 30), (S, 30), (F, 100)]},
}
GROUPS = {"reach": "easy", "assembly": "hard", "basketball": "medium"}


def write_run(
    root,
    objective: str,
    seed: int,
    rollouts: dict,
    *,
    policy: str = "mlp",
    name: str | None = None,
    finished: bool | None = True,
    horizon: int = H,
    eval_seed: int = 1000,
    steps: int = 1000,
    early: dict | None = None,
    weights: pd.DataFrame | None = None,
    final_records: list | None = None,
):
    """A run directory per the recipe's format; ``finished=None`` writes no summary.json (still training).

    ``early``: rollouts of an earlier evaluation at step ``steps // 2`` (must not be used by the report).
    """
    name = name or f"{objective}-{policy}-s{seed}-deadbeef"
    path = root / name
    path.mkdir(parents=True)
    tasks = list(rollouts)
    config = {
        "objective": {"name": objective, "gamma": 1.0, "w_max": 3.0},
        "policy": {"name": policy, "hidden": 256},
        "data": {"tasks": tasks, "n_demos": 10, "seed": 0},
        "eval": {
            "tasks": [],
            "rollouts": len(rollouts[tasks[0]]) if tasks else 4,
            "seed": eval_seed,
            "horizon": horizon,
            "every": 0,
        },
        "optim": {"steps": steps, "lr": 1e-3},
        "seed": seed,
    }
    (path / "config.yaml").write_text(yaml.safe_dump(config))
    rows = []
    for step, per_task in ((steps // 2, early), (steps, rollouts)):
        for task, outcomes in (per_task or {}).items():
            for k, (success, n) in enumerate(outcomes):
                rows.append(
                    {
                        "task": task,
                        "task_id": tasks.index(task),
                        "group": GROUPS[task],
                        "variation_seed": eval_seed,
                        "variation_index": k,
                        "success": success,
                        "steps": n,
                        "rho": n / horizon,
                        "return": 1.0,
                        "failure": "" if success else "timeout",
                        "step": step,
                    }
                )
    columns = ["task", "task_id", "group", "variation_seed", "variation_index", "success", "steps", "rho", "return"]
    pd.DataFrame(rows, columns=[*columns, "failure", "step"]).to_csv(path / "eval_rollouts.csv", index=False)
    metrics = [(steps, "train", "loss", 0.1), (steps, "eval", "success/overall", 0.5)]
    pd.DataFrame(metrics, columns=["step", "phase", "name", "value"]).to_csv(path / "metrics.csv", index=False)
    if weights is not None:
        weights.to_csv(path / "weights.csv", index=False)
    if finished is not None:
        summary = {
            "run_name": name,
            "objective": objective,
            "policy": policy,
            "seed": seed,
            "steps": steps,
            "finished": finished,
            "final": final_records or [],
            "config": config,
            "git_commit": "0123456789abcdef",
            "train_seconds": 12.5,
        }
        (path / "summary.json").write_text(json.dumps(summary))
    return path


def committed_run(run_dir) -> tuple[dict, pd.DataFrame]:
    """A committed run's config (``config.yaml``) and final evaluation: the rows of ``eval_rollouts.csv.gz`` at its
    largest training step, read with yaml and pandas (none of tar-rl's readers)."""
    from pathlib import Path

    run_dir = Path(run_dir)
    config = yaml.safe_load((run_dir / "config.yaml").read_text())
    rollouts = pd.read_csv(run_dir / "eval_rollouts.csv.gz")
    return config, rollouts[rollouts["step"] == rollouts["step"].max()].reset_index(drop=True)
