"""``lerobot-tar``: the plugin's commands (docs/lerobot.md).

* ``lerobot-tar export-dataset FOLDER ROOT``: a tar-rl dataset folder as a LeRobotDataset (:mod:`.export`).
* ``lerobot-tar to-base CHECKPOINT OUT``: a ``*_tar`` checkpoint as its base type, for any LeRobot
  (:mod:`.checkpoints`).
* ``lerobot-tar to-tar CHECKPOINT OUT``: a base checkpoint as its TAR type, to post-train it with
  ``lerobot-train --policy.path=OUT``.
* ``lerobot-tar serve CHECKPOINT``: a state policy answering action chunks for tar-rl's evaluator on stdin and
  stdout (:mod:`.serve`).

A refusal prints one line naming what is wrong and exits with status 1, before anything is written.
"""

from __future__ import annotations

import argparse
import sys

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="lerobot-tar",
        description="The TAR plugin's commands: tar-rl demonstrations as a LeRobotDataset, and checkpoints between "
        "a TAR policy and its base type (docs/lerobot.md).",
    )
    commands = parser.add_subparsers(dest="command", required=True)
    export = commands.add_parser(
        "export-dataset", help="write a tar-rl dataset folder (format 4) as a LeRobotDataset with LeRobot's writer"
    )
    export.add_argument("folder", help="a tar-rl dataset folder (holding metadata.json, digest.json and buffer/)")
    export.add_argument("root", help="the LeRobotDataset's folder, new (lerobot-train's --dataset.root)")
    export.add_argument("--repo-id", help="the dataset's repo_id (--dataset.repo_id; default local/<ROOT's name>)")
    export.add_argument("--fps", type=int, help="frames per second (default: the source's; MetaWorld 80)")
    export.add_argument(
        "--state-dims",
        type=int,
        help="leading observation values that are the robot's state, the rest the environment state "
        "(default: the source's, MetaWorld 4; else all)",
    )
    export.add_argument(
        "--overwrite", action="store_true", help="replace a LeRobotDataset at ROOT (once the new one is complete)"
    )
    base = commands.add_parser("to-base", help="write a *_tar checkpoint as its base type (act_tar -> act, ...)")
    base.add_argument("checkpoint", help="a *_tar checkpoint (its pretrained_model folder or the folder above)")
    base.add_argument("out", help="the new checkpoint's folder (must not exist)")
    tar = commands.add_parser("to-tar", help="write a base checkpoint as its TAR type (act -> act_tar, ...)")
    tar.add_argument("checkpoint", help="an act, diffusion, smolvla, pi0 or pi05 checkpoint folder")
    tar.add_argument("out", help="the new checkpoint's folder (must not exist)")
    serve = commands.add_parser("serve", help="answer action chunks of a state policy on stdin/stdout (framed .npy)")
    serve.add_argument("checkpoint", help="a policy checkpoint (its pretrained_model folder or the folder above)")
    serve.add_argument("--device", default="cpu", help="where the policy runs (default cpu)")
    serve.add_argument("--threads", type=int, help="torch threads (default torch's)")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "serve":
        from .serve import main as serve

        return serve(args.checkpoint, args.device, args.threads)
    from .checkpoints import CheckpointError, to_base, to_tar
    from .export import DatasetError, ExportError, export_dataset

    try:
        if args.command == "export-dataset":
            root = export_dataset(
                args.folder, args.root, repo_id=args.repo_id, fps=args.fps, state_dims=args.state_dims,
                overwrite=args.overwrite,
            )  # fmt: skip
            from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

            meta = LeRobotDatasetMetadata(args.repo_id or f"local/{root.name}", root=root)
            print(
                f"wrote {meta.total_episodes} episodes, {meta.total_frames} frames at {meta.fps} fps, "
                f"{meta.total_tasks} tasks to {root}: lerobot-train --dataset.repo_id={meta.repo_id} "
                f"--dataset.root={root} ..."
            )
        elif args.command == "to-base":
            print(f"wrote {to_base(args.checkpoint, args.out)}: any LeRobot loads it (--policy.path)")
        else:
            out = to_tar(args.checkpoint, args.out)
            print(f"wrote {out}: post-train it with lerobot-train --policy.path={out} --policy.tar.<name>=...")
    except (DatasetError, ExportError, CheckpointError) as error:
        print(f"lerobot-tar {args.command}: {error}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
