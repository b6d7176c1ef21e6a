#!/bin/bash
# One piece of the 2-D walker's PLR⊥ run at DCD's budget, on a machine lent for limited calls
# (docs/running.md, "A run longer than one machine's lease"). Run from the repository root:
#   bash docs/results/bipedal_dcd_plr_inflight/piece.sh SECONDS
# It installs the device's wheels from .whl if present, puts the run's own sources in place (src.tgz:
# shed_jax/, envs/ and experiments/ at commit d1d275c, the sources of ACCEL's run at the same budget, so
# the two compare on one program and later edits to the tree change neither), then starts the run
# (no ckpt.tgz.* here yet) or resumes it from this folder's checkpoint (ckpt.tgz.*, parts of one
# archive) and compilation cache (cache.tgz.*), with --time-limit SECONDS counted from the start of
# this script, and writes the new ckpt.tgz.*, cache.tgz.* and run.log into $OUT; it exits with the
# run's exit code (75: stopped at the time limit and saved). Copy those back over this folder's files
# (old parts removed first) before the next piece.
set -u
: "${1:?usage: bash docs/results/bipedal_dcd_plr_inflight/piece.sh SECONDS}"
# it replaces this tree's sources with the run's: only on the device's copy of the tree, where OUT is set
: "${OUT:?piece.sh runs on the device machine (OUT unset here): it replaces shed_jax/, envs/ and experiments/ in place}"
dir=docs/results/bipedal_dcd_plr_inflight
run=runs/dcd_plr
t0=$(date +%s)
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
  export PYTHONPATH=$PWD:/tmp/site
fi
export PYTHONUNBUFFERED=1 SHED_JAX_CACHE=$PWD/.cache/device
rm -rf shed_jax envs experiments && tar xzf $dir/src.tgz || exit 4
mkdir -p runs .cache
if ls $dir/ckpt.tgz.* >/dev/null 2>&1; then
  cat $dir/ckpt.tgz.* | tar xzf - || exit 5
  what="--resume $run"
else
  what="--env bipedal --method plr --preset dcd --seeds 5 --out $run"
fi
if ls $dir/cache.tgz.* >/dev/null 2>&1; then cat $dir/cache.tgz.* | tar xzf -; fi
lim=$(( $1 - ($(date +%s) - t0) ))
timeout -k 10 $(( lim + 25 )) python -m shed_jax run $what --keep 1 --no-gif --time-limit $lim > $OUT/run.log 2>&1
rc=$?
echo "rc $rc after $(( $(date +%s) - t0 )) s"
# the checkpoint in parts under the 16 MiB a call returns, written whole before it is put in $OUT
if [ -d $run ]; then
  tar czf /tmp/ckpt.tgz $run && gzip -t /tmp/ckpt.tgz && split -b 15M /tmp/ckpt.tgz $OUT/ckpt.tgz. || echo "no checkpoint packed"
  ls -l $OUT/ckpt.tgz.*
fi
tar czf - .cache/device | split -b 15M - $OUT/cache.tgz.
tail -c 2000 $OUT/run.log | tr '\r' '\n' | grep -v '^ *$' | tail -4
exit $rc
