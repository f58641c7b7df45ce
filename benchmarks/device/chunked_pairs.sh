#!/usr/bin/env bash
# Whole seeds of a chunked-heads regime on a lent GPU machine, in one command, from the study commit's code.
#
#   bash benchmarks/device/chunked_pairs.sh REGIME SEEDS JOBS CORES BUDGET_S
#
# Runs from the repository root of a copy of the working tree that holds, besides the tracked files:
#   .whl/     the Python packages the image lacks, as wheels for its Python (torchrl, tensordict, metaworld, ...);
#   wt-gpu/   the study commit's files (`git archive COMMIT`, results left out but for regimes/PLAN.md and
#             chunked_started.json), with the commit's hash in wt-gpu/COMMIT.
# It installs both, trains a ci-scale seed of the regime first (a smoke test of the whole path on this machine:
# CUDA training, evaluation workers, the weighting compiled), then the seeds SEEDS of the regime, JOBS runs at
# once, evaluation workers per run CORES / JOBS. Finished runs are packed into $OUT/runs.tgz as they finish
# (config, summary, per-rollout CSV, metrics, weights; never checkpoints), so a command stopped at its limit
# still returns every finished run. With time left of BUDGET_S seconds, the heads' training steps on CUDA
# are measured (bench_heads.py, the weighting compiled beside eager) into $OUT/heads_cuda.csv.
set -uo pipefail
regime=$1 seeds=$2 jobs=$3 cores=$4 budget=$5
t0=$(date +%s)
log() { echo "[$(( $(date +%s) - t0 ))s] $*"; }
export PYTHONUNBUFFERED=1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*.whl || exit 2
export PYTHONPATH=/tmp/site
rm -rf /tmp/study && cp -r wt-gpu /tmp/study || exit 2
# The study's runs record the commit of the code they run from (git rev-parse HEAD in the package's folder).
(cd /tmp/study && git init -q && cat COMMIT > .git/HEAD && rm COMMIT) || exit 2
# The tree imports unbuilt: tar_rl/objectives, collectors and recipes are links to the root folders.
export PYTHONPATH=/tmp/study:/tmp/site
python3 -P - <<'PY' || exit 2
import torch, torchrl, tensordict, metaworld, mujoco
from tar_rl.runs import git_commit, machine
print("torch", torch.__version__, "torchrl", torchrl.__version__, "tensordict", tensordict.__version__,
      "mujoco", mujoco.__version__, "commit", git_commit(), machine())
PY
nvidia-smi --query-gpu=name,memory.used,memory.total --format=csv,noheader
log "installed"

pack() {  # the finished runs (their summary says so), without checkpoints, into one archive, atomically
  local list
  list=$(cd "$1/runs" 2>/dev/null && grep -l '"finished": true' */summary.json 2>/dev/null | xargs -r -n1 dirname)
  [ -n "$list" ] || return 0
  (cd "$1/runs" && tar czf "$OUT/$2.tmp" --exclude=checkpoint.pt $list) && mv "$OUT/$2.tmp" "$OUT/$2"
  tar czf "$OUT/logs.tmp" -C "$1" logs 2>/dev/null && mv "$OUT/logs.tmp" "$OUT/logs.tgz"
}
drive() {  # SCALE SEEDS OUTDIR STARTED
  python3 -P benchmarks/device/chunked_pairs.py --tree /tmp/study --regime "$regime" --seeds "$2" --out "$3" \
    --data-root /tmp/data --jobs "$jobs" --cores "$cores" --scale "$1" ${4:+--started "$4"}
}

# The smoke test: the ci scale's seed 0, its plan digest recorded here (the ci scale has no record).
ci_digest=$(python3 -P benchmarks/device/chunked_pairs.py --tree /tmp/study --regime "$regime" --seeds 0 \
  --out /tmp/ci --data-root /tmp/data --scale ci --digest) || exit 3
echo "{\"${regime^^}\": \"$ci_digest\"}" > /tmp/ci_started.json
drive ci 0 /tmp/ci /tmp/ci_started.json > /tmp/ci.log 2>&1
rc=$?
pack /tmp/ci ci_runs.tgz
log "smoke test exit $rc"; tail -5 /tmp/ci.log
[ $rc -eq 0 ] || { tail -40 /tmp/ci/logs/*.log; exit 3; }

mkdir -p /tmp/out
drive cpu "$seeds" /tmp/out > "$OUT/driver.log" 2>&1 &
pid=$!
while kill -0 $pid 2>/dev/null; do sleep 10; pack /tmp/out runs.tgz; done
wait $pid
rc=$?
pack /tmp/out runs.tgz
log "study runs exit $rc"; tail -20 "$OUT/driver.log"
nvidia-smi --query-gpu=name,memory.used --format=csv,noheader

left=$(( budget - ($(date +%s) - t0) - 20 ))
if [ $left -gt 60 ]; then
  log "bench_heads for at most ${left}s"
  (cd /tmp/study && timeout $left python3 -P benchmarks/bench_heads.py --device cuda --heads act,flow,octo_linear,octo_diffusion \
    --reps 10 --out "$OUT/heads_cuda.csv") > "$OUT/bench.log" 2>&1
  log "bench_heads exit $?"; tail -30 "$OUT/bench.log"
fi
exit $rc
