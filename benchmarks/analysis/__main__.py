"""``python -m benchmarks.analysis diagnosis [...] | dims --from DIR [...]``: R3 diagnosed (:mod:`.diagnosis`) and
its per-action-dimension recording (:mod:`.dims`)."""

import sys

from benchmarks.analysis import diagnosis, dims

COMMANDS = {"diagnosis": diagnosis.main, "dims": dims.dims_main}
if len(sys.argv) < 2 or sys.argv[1] not in COMMANDS:
    raise SystemExit(f"usage: python -m benchmarks.analysis {' | '.join(COMMANDS)} [options]")
raise SystemExit(COMMANDS[sys.argv[1]](sys.argv[2:]))
