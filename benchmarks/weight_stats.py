"""How concentrated TAR's weights are, per cap mode and temperature, on synthetic segments.

Prints, for segments of L=16 steps with all steps valid, the mean and 99th-percentile of the
largest weight in a segment and the mean effective-sample-size fraction
``(sum w)^2 / (L sum w^2)``, for two loss patterns: log-normal per-step losses, and one step
at 5x the loss of fifteen near-equal steps. Used to choose and document the defaults.

    .venv/bin/python -m benchmarks.weight_stats [--segments 20000] [--w-max 3]
"""

from __future__ import annotations

import argparse

import torch

from tar_rl import tar_weights


def patterns(n: int, length: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
    lognormal = torch.randn(n, length, generator=generator).exp()
    flat = 1 + 0.01 * torch.randn(n, length - 1, generator=generator)
    outlier = torch.cat([flat, torch.full((n, 1), 5.0)], dim=1)
    return {"lognormal(0,1)": lognormal, "one step at 5x": outlier}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--segments", type=int, default=20_000)
    parser.add_argument("--length", type=int, default=16)
    parser.add_argument("--w-max", type=float, default=3.0)
    args = parser.parse_args(argv)
    generator = torch.Generator().manual_seed(0)
    print(f"{'losses':<16} {'gamma':>5} {'cap':<6} {'mean max w':>10} {'p99 max w':>9} {'ESS':>5}")
    for name, losses in patterns(args.segments, args.length, generator).items():
        valid = torch.ones_like(losses, dtype=torch.bool)
        for gamma in (0.5, 1.0, 2.0):
            for cap in ("paper", "exact"):
                w = tar_weights(losses, valid, gamma=gamma, w_max=args.w_max, cap=cap)
                top = w.max(-1).values
                ess = (w.sum(-1) ** 2 / (args.length * w.square().sum(-1))).mean()
                print(f"{name:<16} {gamma:>5} {cap:<6} {top.mean():>10.2f} {top.quantile(0.99):>9.2f} {ess:>5.2f}")


if __name__ == "__main__":
    main()
