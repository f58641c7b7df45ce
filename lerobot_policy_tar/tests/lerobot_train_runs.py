"""``lerobot-train`` command lines, one after another in one process: the plugin's tests start LeRobot once for all
of theirs (the ``lerobot_train`` fixture of ``conftest.py``).

``python lerobot_train_runs.py`` reads one request a line on stdin (JSON: ``{"argv": [...], "out": FOLDER, "cwd":
FOLDER}``) and runs the command line ``lerobot-train ARGV`` in ``cwd`` through ``lerobot-train``'s own entry point,
the function its console script calls (looked up in the installed entry points, so the path is the one the user's
command takes: LeRobot's plugin discovery, its config parser, ``train``). The run's stdout and stderr (the file
descriptors, so LeRobot's logging and any library's prints) go to ``FOLDER/stdout`` and ``FOLDER/stderr``; its exit
status, the console script's (1 for an exception, its traceback in ``stderr`` as the console script prints it; else
the ``SystemExit`` code or 0), is the answer: a line ``STATUS <n>`` on stdout. The process loads the entry point
(LeRobot's import) as it starts, before the first request; anything printed outside a run goes to its stderr.
"""

from __future__ import annotations

import json
import os
import sys
import traceback
from importlib.metadata import entry_points
from pathlib import Path


def run(main, argv: list[str], out: Path, cwd: str) -> int:
    out.mkdir(parents=True, exist_ok=True)
    sys.stdout.flush()
    sys.stderr.flush()
    saved = os.dup(1), os.dup(2)
    before = os.getcwd()
    with open(out / "stdout", "wb") as stdout, open(out / "stderr", "wb") as stderr:
        os.dup2(stdout.fileno(), 1)
        os.dup2(stderr.fileno(), 2)
        os.chdir(cwd)
        sys.argv = ["lerobot-train", *argv]
        try:
            main()
            status = 0
        except SystemExit as exit_:
            status = exit_.code if isinstance(exit_.code, int) else (0 if exit_.code is None else 1)
            if not isinstance(exit_.code, int | None):
                print(exit_.code, file=sys.stderr)  # as Python prints sys.exit("message")
        except BaseException:
            traceback.print_exc()
            status = 1
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.chdir(before)
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            os.close(saved[0])
            os.close(saved[1])
    return status


if __name__ == "__main__":
    answers = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)  # stdout outside a run: stderr, so the answers are alone on the pipe
    (main,) = (point.load() for point in entry_points(group="console_scripts", name="lerobot-train"))
    for request in sys.stdin:
        case = json.loads(request)
        status = run(main, case["argv"], Path(case["out"]), case["cwd"])
        print(f"STATUS {status}", file=answers, flush=True)
