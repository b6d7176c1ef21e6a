#!/bin/bash
# Compile a carried run's programs on this CPU host for the GPU that a probe describes, into the run
# folder's compilation cache (experiments/aot_cache.py says how and why). Run from the repository root:
#   AOT_PYTHON=PY bash experiments/aot_fill.sh FOLDER PROBE.json [--chunks]
# PY is a Python with the GPU host's jax, jaxlib and jax-cuda plugin versions (the probe names jax's;
# docs/running.md has the set-up). The run's sources (FOLDER/src.tgz) are put at the path the GPU host
# ran them from (the probe's "root"), through a private mount: kernel IR holds source paths, so the
# programs are the GPU host's only there. The filled cache goes to FOLDER/gpu-MODEL/cache.tgz.*, MODEL
# the probed GPU's (experiments/gpu_model.sh: h100, h200, ...), where run_piece.sh looks for it on a
# host with that GPU; what that folder's cache held is kept (FOLDER's own cache.tgz.* is left alone:
# it holds the programs of the GPU the run began on). aot_report.json beside the parts says the
# compile times and whether the initial state's key matched the probe's; when it did not (exit status
# 1), aot_fill_init.mlir.gz beside it is the program's text, to diff with the probe's
# aot_probe_init.mlir.gz. Exit status: aot_cache.py's.
set -u
usage="usage: AOT_PYTHON=PY bash experiments/aot_fill.sh FOLDER PROBE.json [--chunks]"
dir=${1:?$usage}
probe=${2:?$usage}
shift 2
py=${AOT_PYTHON:?"aot_fill: set AOT_PYTHON to a Python with the GPU host's jax, jaxlib and CUDA plugin ($usage)"}
[ -f "$dir/run.args" ] && [ -f "$dir/src.tgz" ] || { echo "aot_fill: $dir lacks run.args or src.tgz"; exit 2; }
[ -f "$probe" ] || { echo "aot_fill: no probe file $probe"; exit 2; }
[ "$(id -u)" = 0 ] || { echo "aot_fill: needs root for its private mount (unshare -m)"; exit 2; }
root=$(python3 -c 'import json, sys; print(json.load(open(sys.argv[1]))["root"])' "$probe") || exit 2
model=$(bash "$(dirname "$0")/gpu_model.sh" "$(python3 -c 'import json, sys; print(json.load(open(sys.argv[1]))["device_kind"])' "$probe")")
[ -n "$model" ] || { echo "aot_fill: $probe names no GPU model (device_kind)"; exit 2; }
dest=$dir/gpu-$model
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
tar xzf "$dir/src.tgz" -C "$work" || exit 4
cp "$dir/run.args" "$work/run.args"
cp experiments/aot_cache.py "$work/.aot_cache.py"
cp "$probe" "$work/probe.json"
if ls "$dest"/cache.tgz.* >/dev/null 2>&1; then cat "$dest"/cache.tgz.* | tar xzf - -C "$work" || exit 5; fi
envs=(PYTHONUNBUFFERED=1 "PYTHONPATH=$root" "SHED_JAX_CACHE=$root/.cache/device" JAX_PLATFORMS=cpu)
if [ -f "$dir/run.env" ]; then
  while IFS= read -r line; do
    case $line in ''|'#'*) ;; *) envs+=("$line");; esac
  done < "$dir/run.env"
fi
mkdir -p "$root"
unshare -m --propagation private env "${envs[@]}" bash -c \
  'mount --bind "$0" "$1" && cd "$1" && exec "$2" .aot_cache.py fill run.args probe.json --out aot_report.json "${@:3}"' \
  "$work" "$root" "$py" "$@"
rc=$?
mkdir -p "$dest"
# an earlier fill's report stays beside it, named by its date (aot_report_YYYY-MM-DD_HHMM.json)
if [ -f "$work/aot_report.json" ] && [ -f "$dest/aot_report.json" ]; then
  when=$(python3 -c 'import json, sys; print(json.load(open(sys.argv[1]))["date"].replace(" UTC", "").replace(" ", "_").replace(":", ""))' "$dest/aot_report.json" 2>/dev/null)
  mv "$dest/aot_report.json" "$dest/aot_report_${when:-earlier}.json"
fi
cp "$work/aot_report.json" "$dest/aot_report.json" 2>/dev/null
# a key that differs: the program's text beside the report, to diff with the probe's aot_probe_init.mlir.gz
[ "$rc" = 1 ] && cp "$work/aot_fill_init.mlir.gz" "$dest/" 2>/dev/null
if [ "$rc" = 0 ] && [ -d "$work/.cache/device" ]; then  # a fill that the GPU would miss is not kept
  # once the run has a checkpoint, XLA's kernel cache file (tens of MB) is left out, as run_piece.sh
  # packs it: it serves only compiles of programs not in the cache
  skip=()
  ls "$dir"/ckpt.tgz.* >/dev/null 2>&1 && skip=(--exclude=xla_gpu_kernel_cache_file)
  (cd "$work" && tar czf - "${skip[@]}" .cache/device | split -b 15M - "$work/cache.tgz.") || exit 6
  rm -f "$dest"/cache.tgz.*
  cp "$work"/cache.tgz.* "$dest"/
  ls -l "$dest"/cache.tgz.*
fi
exit $rc
