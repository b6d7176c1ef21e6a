#!/bin/bash
# Takes what one piece of experiments/run_piece.sh returned into the run's folder, for the next piece.
# Run from the repository root:
#   bash experiments/adopt_piece.sh FOLDER FROM
# FROM is where the piece's files came back (the device call's files_at): cache.tgz.* (none from a run
# that finished: FOLDER keeps its cache), run.log, gpu and,
# when the run saved, ckpt.tgz.*; with AOT_PROBE=1 or AOT_GATE=1, aot_probe.json where the carried cache did
# not serve the host (copied too; where it did, the probe is at the end of run.log). Every archive is checked whole (gzip -t) before FOLDER is touched;
# then FOLDER's old parts of each returned archive are removed (the split may change) and the new ones
# copied in. A piece without a checkpoint (its compile cut off, or its call ended before it saved)
# leaves FOLDER's checkpoint as it was. Prints the run log's compile and last progress lines (for the
# folder's table) and the size the tree now carries to the device with the wheels (64 MiB at most).
set -u
usage="usage: bash experiments/adopt_piece.sh FOLDER FROM"
dir=${1:?$usage}
from=${2:?$usage}
[ -f "$dir/run.args" ] || { echo "adopt_piece: $dir is not a carried run's folder (no run.args)"; exit 2; }
kinds=()
ls "$from"/cache.tgz.* >/dev/null 2>&1 && kinds+=(cache)
ls "$from"/ckpt.tgz.* >/dev/null 2>&1 && kinds+=(ckpt)
[ "${#kinds[@]}" -gt 0 ] || { echo "adopt_piece: $from holds no cache.tgz.* and no ckpt.tgz.* (nothing came back from the piece?)"; exit 2; }
for k in "${kinds[@]}"; do
  cat "$from"/$k.tgz.* | gzip -t 2>/dev/null || { echo "adopt_piece: $from/$k.tgz.* is not a whole gzip archive; $dir left as it was"; exit 3; }
done
# the cache goes back where the piece took it from: FOLDER/gpu-MODEL/ when the folder has one for
# the GPU the piece ran on (its $OUT/gpu), else FOLDER itself. Without FROM/gpu (a call returns 8
# files and may leave it out) the model is unknown, and a folder with caches per model is not guessed at
if [ ! -f "$from/gpu" ] && ls -d "$dir"/gpu-*/ >/dev/null 2>&1; then
  echo "adopt_piece: $from has no gpu file, and $dir keeps a cache per GPU model: write the model that ran the piece (e.g. echo h100 > $from/gpu; its device line says which) and run again; $dir left as it was"
  exit 2
fi
cdir=$dir
if [ -f "$from/gpu" ] && [ -d "$dir/gpu-$(cat "$from/gpu")" ]; then cdir=$dir/gpu-$(cat "$from/gpu"); fi
for k in "${kinds[@]}"; do
  to=$dir
  [ "$k" = cache ] && to=$cdir
  rm -f "$to"/$k.tgz.*
  for part in "$from"/$k.tgz.*; do
    cp "$part" "$to/" && chmod u+w "$to/$(basename "$part")"
  done
  echo "$k: $(ls "$to"/$k.tgz.* | wc -l) part(s), $(cat "$to"/$k.tgz.* | wc -c) bytes$( [ -f "$from/gpu" ] && echo " (ran on $(cat "$from/gpu"))") in $to"
done
case " ${kinds[*]} " in *" ckpt "*) ;; *) echo "ckpt: none returned; $dir keeps its checkpoint";; esac
case " ${kinds[*]} " in *" cache "*) ;; *) echo "cache: none returned (a run that finished packs none); $dir keeps its cache";; esac
# a piece run with AOT_PROBE=1: its probe of the GPU host's key parts (a few kB), for experiments/aot_fill.sh
if [ -f "$from/aot_probe.json" ]; then cp "$from/aot_probe.json" "$dir/" && chmod u+w "$dir/aot_probe.json" && echo "aot probe: $dir/aot_probe.json"; fi
if [ -f "$from/run.log" ]; then
  tr '\r' '\n' < "$from/run.log" | grep -a -E 'compiled in|stand-in' | head -3  # how the chunk was had
  tr '\r' '\n' < "$from/run.log" | grep -a -E '^step |stopped at|still compiling' | tail -3
fi
if git rev-parse --git-dir >/dev/null 2>&1; then
  total=$(bash "$(dirname "$0")/carried_size.sh")
  echo "the tree carries $total bytes with the wheels (limit $(( 64 * 1024 * 1024 )))"
  [ "$total" -le $(( 64 * 1024 * 1024 )) ] || echo "adopt_piece: over the 64 MiB a device call carries: move a folder that is not being run out of the tree for the call"
fi
exit 0
