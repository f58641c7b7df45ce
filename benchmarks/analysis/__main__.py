"""``python -m benchmarks.analysis diagnosis [--regime R4] [...] | dims --from DIR [...] | noise --from DIR [...]``: a
regime diagnosed (:mod:`.diagnosis`; R3 by default), R3's per-action-dimension recording (:mod:`.dims`), and how
much of TAR's weighting a head's random draw decides (:mod:`.noise`)."""

import sys

from benchmarks.analysis import diagnosis, dims, noise

COMMANDS = {"diagnosis": diagnosis.main, "dims": dims.dims_main, "noise": noise.noise_main}
if len(sys.argv) < 2 or sys.argv[1] not in COMMANDS:
    raise SystemExit(f"usage: python -m benchmarks.analysis {' | '.join(COMMANDS)} [options]")
raise SystemExit(COMMANDS[sys.argv[1]](sys.argv[2:]))
