#!/bin/bash
# One program at several seed counts, timed on one GPU: each FOLDER is a carried run's folder (run.args
# with its own --seeds, src.tgz, a cache filled on a CPU host by aot_fill.sh) that has not started;
# each runs as a fresh run's first piece (experiments/run_piece.sh) for SECONDS, one after another, and
# its run.log comes back as $OUT/NAME.log (NAME: the folder's base name). Its checkpoint and cache do
# not: this measures, it carries nothing on. Then, here:
#   python -m experiments.seeds_scaling $FILES_AT/*.log --out RECORD.json
# Run from the repository root on the device machine (a disposable copy: OUT must be set):
#   OUT=DIR bash experiments/seeds_scaling.sh SECONDS FOLDER [FOLDER ...]
# SECONDS per folder, run_piece.sh's: its set-up (reading the programs, about 100 s on an H100) and
# packing included. Exit: 0 when every piece stopped at its limit (75) or finished; 1 otherwise.
set -u
usage="usage: OUT=DIR bash experiments/seeds_scaling.sh SECONDS FOLDER [FOLDER ...]"
secs=${1:?$usage}
shift
[ $# -ge 1 ] || { echo "$usage"; exit 2; }
: "${OUT:?seeds_scaling.sh runs pieces, which replace shed_jax/, envs/ and experiments/ in place: run it on a disposable copy with OUT set}"
bad=0
for f in "$@"; do
  f=${f%/}
  [ -f "$f/run.args" ] || { echo "seeds_scaling: $f has no run.args"; bad=1; continue; }
  ls "$f"/ckpt.tgz.* >/dev/null 2>&1 && { echo "seeds_scaling: $f has a checkpoint: a fresh run is timed here"; bad=1; continue; }
  scratch=$(mktemp -d)
  OUT=$scratch AOT_GATE=1 CHECKPOINT_EVERY=100000 bash experiments/run_piece.sh "$f" "$secs"
  rc=$?
  cp "$scratch/run.log" "$OUT/$(basename "$f").log" 2>/dev/null || echo "seeds_scaling: $f left no run.log"
  rm -rf "$scratch"
  echo "seeds_scaling: $f exited $rc"
  case $rc in 0|75) ;; *) bad=1;; esac
done
exit $bad
