#!/usr/bin/env bash
# Lays out, in this checkout, what benchmarks/device/chunked_pairs.sh needs on a lent GPU machine whose image has
# Python 3.12 and a CUDA build of torch but none of tar-rl's other packages, and reaches no package registry:
#
#   bash benchmarks/device/prepare.sh [STUDY_COMMIT]       (default 2a4022e, the chunked-heads regimes' commit)
#
#   .whl/    wheels for CPython 3.12 on x86-64 Linux of the packages the image lacks (about 47 MB);
#   wt-gpu/  the study commit's files without its results, but for regimes/PLAN.md and this checkout's
#            chunked_started.json (the plan record the driver checks), with the commit's hash in wt-gpu/COMMIT.
#
# Both are left out of git by .git/info/exclude. The device machine takes at most 64 MiB of working tree, and the
# committed results alone are larger: for the call, leave them out of the index and of the copy, and put them back
# after it (the files themselves stay where they are):
#
#   echo /benchmarks/results/ >> .git/info/exclude && git rm -r -q --cached benchmarks/results
#   ... run: bash benchmarks/device/chunked_pairs.sh r5 0,1,2 9 32 545   (carry .whl and wt-gpu; timeout 570 s)
#   git reset -q && sed -i '\|^/benchmarks/results/$|d' .git/info/exclude
set -euo pipefail
cd "$(dirname "$0")/../.."
commit=$(git rev-parse "${1:-2a4022e}")
exclude=$(git rev-parse --git-path info/exclude)
grep -qx '/.whl/' "$exclude" || echo /.whl/ >> "$exclude"
grep -qx '/wt-gpu/' "$exclude" || echo /wt-gpu/ >> "$exclude"
mkdir -p .whl
platforms=()
for p in manylinux_2_17_x86_64 manylinux2014_x86_64 manylinux_2_28_x86_64 manylinux_2_34_x86_64; do
  platforms+=(--platform "$p")
done
# torchrl and tensordict as tar-rl pins them; metaworld pins mujoco; the rest are what these import.
for pkg in torchrl==0.14.1 tensordict==0.14.3 metaworld==3.1.1 mujoco==3.3.0 gymnasium==1.4.0 hydra-core==1.3.2 \
  omegaconf==2.3.0 hydra-joblib-launcher==1.2.0 farama-notifications==0.0.6 pyvers==0.2.3 hoptorch==0.1.4 \
  orjson==3.13.0 importlib_metadata==10.2.0 glfw==2.11.0; do
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    "${platforms[@]}" -d .whl "$pkg"
done
python3 -m pip wheel -q --no-deps -w .whl antlr4-python3-runtime==4.9.3  # published as a source archive only
rm -rf wt-gpu && mkdir wt-gpu
git archive "$commit" | tar -x -C wt-gpu --exclude='benchmarks/results/*'
mkdir -p wt-gpu/benchmarks/results/regimes
git show "$commit:benchmarks/results/regimes/PLAN.md" > wt-gpu/benchmarks/results/regimes/PLAN.md
cp benchmarks/results/regimes/chunked_started.json wt-gpu/benchmarks/results/regimes/
echo "$commit" > wt-gpu/COMMIT
du -sh .whl wt-gpu
