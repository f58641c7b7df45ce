"""The tables and figures of the paper's experiments (:mod:`.paper`), written from finished runs: Table I with
Figs. 3-4, Table III, the critical windows with Fig. 5, the budget curve and the sensitivity grid. Each writer takes
the runs' specs, the output folder and the provenance, and writes its files atomically; runs that have not finished
are listed under the table, never silently left out.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from benchmarks.studies.core import Spec
from benchmarks.studies.protocol import BASELINE, TREATMENT
from benchmarks.studies.writers import controls_markdown, table_one_markdown
from tar_rl.report.figures import (
    plot_critical_windows,
    plot_group_deltas,
    plot_heatmaps,
    plot_lines,
    plot_radar,
    plot_weight_phases,
)
from tar_rl.report.weight_phases import critical_windows, phase_weight_mass

__all__ = [
    "report_budget",
    "report_controls",
    "report_critical_windows",
    "report_sensitivity",
    "report_table",
    "start_output",
]


def _caption(prov: dict) -> str:
    return (
        f"{prov['command']} | git {str(prov['git_commit'])[:10]} | scale {prov['scale']} | "
        f"{prov['hostname']}, {prov['cores']} cores, torch {prov['torch']}, {prov['device']}"
    )


def _prov_markdown(prov: dict) -> str:
    return (
        f"Command: `{prov['command']}`  \nGit commit: `{prov['git_commit']}`; scale: `{prov['scale']}` "
        f"({prov['scale_about']})  \nMachine: {prov['hostname']}, {prov['cores']} cores, {prov['platform']}, "
        f"torch {prov['torch']}, device {prov['device']}; written {prov['written']}"
    )


def _write_text(path: Path, text: str) -> Path:
    from tar_rl.io import atomic_write

    return atomic_write(path, lambda f: f.write(text))


def start_output(folder: Path, prov: dict) -> None:
    from tar_rl.io import write_json_atomic

    folder.mkdir(parents=True, exist_ok=True)
    write_json_atomic(prov, folder / "provenance.json")


def _load(specs: Sequence[Spec]):
    """The finished runs of ``specs`` (loaded) and the names of the others."""
    from tar_rl.report import load_run

    runs, missing = [], []
    for spec in {s.run_dir: s for s in specs}.values():
        if spec.finished:
            runs.append(load_run(spec.run_dir))
        else:
            missing.append(spec.run_dir.name)
    return runs, missing


def _missing_note(missing: Sequence[str]) -> str:
    if not missing:
        return ""
    shown = ", ".join(missing[:10]) + (f" (+{len(missing) - 10} more)" if len(missing) > 10 else "")
    return f"\n\n**Incomplete**: {len(missing)} planned run(s) have not finished and are not included: {shown}."


# -- Reports ---------------------------------------------------------------------------------------


def report_table(specs: Sequence[Spec], folder: Path, prov: dict) -> dict[str, Path]:
    """Table I (markdown + CSV), the paired statistics, Fig. 3 and Fig. 4 from the protocol runs."""
    from tar_rl.io import write_csv_atomic
    from tar_rl.report import compare, paired_table, plot_success_vs_neps

    runs, missing = _load(specs)
    if not runs:
        raise SystemExit("paper: no finished protocol run yet; run the `protocol` stage first")
    table = compare(runs)
    paired = paired_table(runs, objectives=[TREATMENT])
    out = {
        "table_I.csv": write_csv_atomic(table, folder / "table_I.csv"),
        "paired.csv": write_csv_atomic(paired, folder / "paired.csv"),
    }
    md = (
        "# Table I: uniform vs TAR per policy family\n\n"
        "Success % per difficulty group and overall; 100 x Fast20 and 100 x NEPS (lower is better). "
        "Rows: mean ± std over the paired seeds; Δ: mean paired difference (TAR - uniform) with its 95% CI "
        "(t quantile, n - 1 degrees of freedom); p: two-sided paired t-test. "
        f"Evaluation seed {runs[0].eval_settings.get('eval.seed')}, "
        f"{runs[0].eval_settings.get('eval.rollouts')} rollouts per task, "
        f"{len(runs[0].eval_settings.get('tasks', ()))} tasks.\n\n"
        + table_one_markdown(paired, TREATMENT)
        + _missing_note(missing)
        + "\n\n"
        + _prov_markdown(prov)
        + "\n"
    )
    out["table_I.md"] = _write_text(folder / "table_I.md", md)
    caption = _caption(prov)
    out["fig3"] = plot_success_vs_neps(
        table[table["objective"].isin([BASELINE, TREATMENT])], folder / "fig3_success_vs_neps.png", caption=caption
    )
    out["fig3c"] = plot_group_deltas(paired, folder / "fig3c_group_deltas.png", TREATMENT, caption=caption)
    try:
        out["fig4"] = plot_radar(table, folder / "fig4_radar.png", TREATMENT, caption=caption)
    except ValueError as err:
        print(f"note: Fig. 4 not drawn: {err}")
    print(md)
    return out


def report_controls(specs: Sequence[Spec], folder: Path, prov: dict, family: str) -> dict[str, Path]:
    """Table III for one family: every weighting, success per group, paired difference to uniform."""
    from tar_rl.io import write_csv_atomic
    from tar_rl.report import compare, paired_table

    runs, missing = _load(specs)
    if not runs:
        raise SystemExit("paper: no finished control run yet")
    table = compare(runs)
    paired = paired_table(runs)
    md = (
        f"# Table III: controls ({family})\n\n"
        "Success % (mean ± std over seeds) per difficulty group and overall, and the paired difference of the "
        "overall success to uniform (95% CI, paired t-test).\n\n"
        + controls_markdown(paired, table, family)
        + _missing_note(missing)
        + "\n\n"
        + _prov_markdown(prov)
        + "\n"
    )
    out = {
        "table_III.csv": write_csv_atomic(table, folder / "table_III.csv"),
        "paired.csv": write_csv_atomic(paired, folder / "paired.csv"),
        "table_III.md": _write_text(folder / "table_III.md", md),
    }
    print(md)
    return out


def report_critical_windows(specs: Sequence[Spec], folder: Path, prov: dict, tasks: Sequence[str]) -> dict[str, Path]:
    """Phase shares of TAR weight mass per task (table, figure) and Fig. 5, from the TAR runs' weights.csv."""
    from tar_rl.io import write_csv_atomic
    from tar_rl.report import PHASES

    runs, missing = _load([s for s in specs if s.config["objective"]["name"] == TREATMENT])
    runs = [r for r in runs if r.weights is not None]
    if not runs:
        raise SystemExit("paper: no finished TAR run with recorded weights (weights.csv) yet")
    frames = [r.weights.assign(run=r.name) for r in sorted(runs, key=lambda r: (r.policy, r.seed))]
    mass = phase_weight_mass(pd.concat(frames, ignore_index=True))
    windows = critical_windows(mass)
    header = "| task | demos | with grip | " + " | ".join(p.replace("_", " ") for p in PHASES) + " | peak |"
    lines = [header, "|" + "---|" * (4 + len(PHASES))]
    for rec in windows.to_dict("records"):
        cells = [
            "-" if rec[f"{p}_steps"] == 0 else f"{100 * rec[f'{p}_weight']:.0f}% / {100 * rec[f'{p}_steps']:.0f}%"
            for p in PHASES
        ]
        lines.append(
            f"| {rec['task']} | {rec['demos']} | {rec['with_anchor']} | " + " | ".join(cells) + f" | {rec['peak']} |"
        )
    md = (
        "# Critical windows: where TAR's weights concentrate\n\n"
        "Per task, over the recorded demonstrations of the TAR runs (weights at the last training step): share of "
        "the TAR weight mass / share of the steps in each phase. Phases from the gripper action (action[3]): "
        "contact onset = the steps within 10% of the demonstration's length of the first gripper-closing step, "
        "approach before it, completion = the last 15% of the steps, transport between. Tasks without a closing "
        "step have only approach and completion. peak: the phase with the largest weight/step ratio.\n\n"
        + "\n".join(lines)
        + _missing_note(missing)
        + "\n\n"
        + _prov_markdown(prov)
        + "\n"
    )
    caption = _caption(prov)
    out = {
        "critical_windows.csv": write_csv_atomic(windows, folder / "critical_windows.csv"),
        "phase_mass.csv": write_csv_atomic(mass, folder / "phase_mass.csv"),
        "critical_windows.md": _write_text(folder / "critical_windows.md", md),
        "critical_windows.png": plot_critical_windows(windows, folder / "critical_windows.png", caption=caption),
    }
    from tar_rl.collectors.metaworld.tasks import resolve_tasks

    first = min(runs, key=lambda r: (r.policy, r.seed))
    wanted = [resolve_tasks([t])[0] for t in tasks]  # "reach" -> "reach-v3", in the order given
    recorded = sorted(set(first.weights["task"]))
    present = [t for t in wanted if t in recorded]
    if len(present) < min(3, len(wanted)):  # fill up with recorded tasks, so that the figure always shows some
        present += [t for t in recorded if t not in present][: min(3, len(wanted)) - len(present)]
    if present:
        out["fig5"] = plot_weight_phases(
            first.weights, folder / "fig5_weights.png", present, caption=f"run {first.name} | {caption}"
        )
    print(md)
    return out


def report_budget(specs: Sequence[Spec], folder: Path, prov: dict) -> dict[str, Path]:
    """Success vs demonstrations per task for uniform and TAR (mean ± std over seeds, paired difference)."""
    from tar_rl.io import write_csv_atomic
    from tar_rl.report import paired_t, run_percent

    runs, missing = _load(specs)
    if not runs:
        raise SystemExit("paper: no finished budget run yet")
    rows = []
    by = {}
    for r in runs:
        by.setdefault(int(r.config["data"]["n_demos"]), {}).setdefault(r.objective, {})[r.seed] = r
    for n in sorted(by):
        for objective, seeds in by[n].items():
            vals = [run_percent(seeds[s])[("success", "overall")] for s in sorted(seeds)]
            rows.append(
                {
                    "n_demos": n,
                    "objective": objective,
                    "n_seeds": len(vals),
                    "mean": sum(vals) / len(vals),
                    "std": pd.Series(vals).std(ddof=1) if len(vals) > 1 else math.nan,
                }
            )
    df = pd.DataFrame(rows)
    lines = ["| demos per task | uniform | tar | Δ tar - uniform [95% CI] | p | pairs |", "|---|---|---|---|---|---|"]
    for n in sorted(by):
        b, t = by[n].get(BASELINE, {}), by[n].get(TREATMENT, {})
        shared = sorted(set(b) & set(t))
        d = [run_percent(t[s])[("success", "overall")] - run_percent(b[s])[("success", "overall")] for s in shared]
        st = paired_t(d)

        def mean_sd(obj, n=n):
            m = df[(df["n_demos"] == n) & (df["objective"] == obj)]
            if m.empty:
                return "-"
            sd = m["std"].iloc[0]
            return f"{m['mean'].iloc[0]:.1f}" + ("" if math.isnan(sd) else f" ± {sd:.1f}")

        ci = "" if math.isnan(st["ci_low"]) else f" [{st['ci_low']:+.2f}, {st['ci_high']:+.2f}]"
        delta = "-" if not shared else f"{st['mean']:+.2f}{ci}"
        p = "-" if math.isnan(st["p_value"]) else f"{st['p_value']:.3f}"
        lines.append(f"| {n} | {mean_sd(BASELINE)} | {mean_sd(TREATMENT)} | {delta} | {p} | {len(shared)} |")
    md = (
        "# Demonstration budget: overall success % vs demonstrations per task\n\n"
        + "\n".join(lines)
        + _missing_note(missing)
        + "\n\n"
        + _prov_markdown(prov)
        + "\n"
    )
    out = {
        "budget.csv": write_csv_atomic(df, folder / "budget.csv"),
        "budget.md": _write_text(folder / "budget.md", md),
        "budget.png": plot_lines(
            df,
            folder / "budget.png",
            "n_demos",
            "demonstrations per task",
            "overall success (%)",
            "Success vs demonstration budget (mean ± std over seeds)",
            caption=_caption(prov),
        ),
    }
    print(md)
    return out


def report_sensitivity(specs: Sequence[Spec], folder: Path, prov: dict, eval_seed: int) -> dict[str, Path]:
    """The gamma x w_max x cap grid: overall success and the paired difference to uniform per cell."""
    from tar_rl.io import write_csv_atomic
    from tar_rl.report import paired_t, run_percent

    runs, missing = _load(specs)
    if not runs:
        raise SystemExit("paper: no finished sensitivity run yet")
    base = {r.seed: run_percent(r)[("success", "overall")] for r in runs if r.objective == BASELINE}
    cells: dict[tuple, dict[int, float]] = {}
    for r in runs:
        if r.objective != TREATMENT:
            continue
        o = r.config["objective"]
        cells.setdefault((float(o["gamma"]), float(o["w_max"]), str(o["cap"])), {})[r.seed] = run_percent(r)[
            ("success", "overall")
        ]
    rows = []
    for (g, w, c), seeds in sorted(cells.items()):
        shared = sorted(set(seeds) & set(base))
        st = paired_t([seeds[s] - base[s] for s in shared])
        rows.append(
            {
                "gamma": g,
                "w_max": w,
                "cap": c,
                "n_seeds": len(seeds),
                "success": sum(seeds.values()) / len(seeds),
                "uniform": sum(base[s] for s in shared) / len(shared) if shared else math.nan,
                "n_pairs": len(shared),
                "delta": st["mean"],
                "ci_low": st["ci_low"],
                "ci_high": st["ci_high"],
                "p_value": st["p_value"],
            }
        )
    df = pd.DataFrame(rows)
    lines = ["| gamma | w_max | cap | success % | Δ vs uniform [95% CI] | pairs |", "|---|---|---|---|---|---|"]
    for rec in rows:
        ci = "" if math.isnan(rec["ci_low"]) else f" [{rec['ci_low']:+.2f}, {rec['ci_high']:+.2f}]"
        delta = "-" if not rec["n_pairs"] else f"{rec['delta']:+.2f}{ci}"
        lines.append(
            f"| {rec['gamma']:g} | {rec['w_max']:g} | {rec['cap']} | {rec['success']:.1f} | {delta} "
            f"| {rec['n_pairs']} |"
        )
    md = (
        "# Sensitivity of TAR to gamma, w_max and the cap mode\n\n"
        f"**Tuning set**: evaluated on eval.seed = {eval_seed} (variations not used by the final tables, which "
        "use eval.seed = 1000). Uniform (same seeds, same evaluation): "
        + (", ".join(f"seed {s}: {v:.1f}%" for s, v in sorted(base.items())) or "-")
        + ".\n\n"
        + "\n".join(lines)
        + _missing_note(missing)
        + "\n\n"
        + _prov_markdown(prov)
        + "\n"
    )
    out = {
        "sensitivity.csv": write_csv_atomic(df, folder / "sensitivity.csv"),
        "sensitivity.md": _write_text(folder / "sensitivity.md", md),
    }
    if len(df):
        out["sensitivity.png"] = plot_heatmaps(
            df,
            folder / "sensitivity.png",
            "gamma",
            "w_max",
            "cap",
            "delta",
            f"TAR - uniform, overall success (pp), tuning eval seed {eval_seed}",
            caption=_caption(prov),
        )
    print(md)
    return out
