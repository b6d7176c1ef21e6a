#!/bin/bash
# One piece of a run too long for one machine's lease (docs/running.md, "A run longer than one
# machine's lease"), carried across leases in a folder of its own. Run from the repository root:
#   OUT=DIR bash experiments/run_piece.sh FOLDER SECONDS
# FOLDER holds: run.args (the flags that start the run, `--out runs/NAME` among them), src.tgz (the
# run's own shed_jax/, envs/ and experiments/, so later edits to the tree change neither the program
# nor its compilation-cache keys), optionally run.env (NAME=VALUE lines exported for every piece, e.g.
# JAX_PERSISTENT_CACHE_ENABLE_XLA_CACHES=all: settings that change cache keys must not change between
# pieces), and after the first piece ckpt.tgz.* (parts of one archive of the run directory) and
# cache.tgz.* (JAX's persistent compilation cache, with what XLA keeps there: autotuning results, and
# its kernel cache where run.env asks for it; packed also after a compile the piece's limit cut off),
# and optionally gpu-MODEL/cache.tgz.*, the cache a host with that GPU model reads instead (below).
# The script installs the wheels in .whl if there are any, puts the run's sources in place OF THIS
# TREE'S (so OUT must be set: it runs on a disposable copy, e.g. the device machine's), starts the run
# (no ckpt.tgz.* yet) or resumes it, stops it with --time-limit SECONDS counted from the script's
# start, and writes the new ckpt.tgz.*, cache.tgz.* (not once the run has finished), run.log and gpu (the GPU model) into $OUT. SECONDS is the whole
# piece, packing included: the run stops PACK_S (45) seconds before it, which covers the checkpoint
# the run writes when it stops (about 15 s for SHED on the 2-D walker) and the packing. Give it the
# device call's limit_s less about 20 s: a call ended by its limit returns nothing of the piece. It exits with the run's exit code (75: stopped at
# the time limit and saved; 0: finished, final evaluation included; 2: bad arguments; 6 and 7:
# AOT_GATE=1 and the carried cache does not serve this host, nothing run or the run stopped before
# compiling its chunk; 8: parts the folder left out of this call are not staged on this machine, nothing run). CHECKPOINT_EVERY (seconds, default 120): how often the run saves besides at
# its stop. Copy those
# back over FOLDER's parts (old parts removed first: the split may change) before the next piece.
set -u
usage="usage: OUT=DIR bash experiments/run_piece.sh FOLDER SECONDS"
dir=${1:?$usage}
secs=${2:?$usage}
case $secs in ''|*[!0-9]*) echo "run_piece: SECONDS must be a whole number, got '$secs'"; exit 2;; esac
every=${CHECKPOINT_EVERY:-120}
case $every in ''|*[!0-9]*) echo "run_piece: CHECKPOINT_EVERY must be a whole number of seconds, got '$every'"; exit 2;; esac
[ "$secs" -gt "${PACK_S:-45}" ] || { echo "run_piece: SECONDS=$secs leaves no time to run: the last ${PACK_S:-45} s are kept for the checkpoint and the packing"; exit 2; }
# it replaces this tree's sources with the run's: only on a disposable copy of the tree, where OUT is set
: "${OUT:?run_piece.sh replaces shed_jax/, envs/ and experiments/ in place: run it on a disposable copy with OUT set}"
[ -f "$dir/run.args" ] && [ -f "$dir/src.tgz" ] || { echo "run_piece: $dir lacks run.args or src.tgz"; exit 2; }
# run.env is sourced: plain NAME=VALUE lines only (no spaces, quotes or shell syntax), comments, blanks
if [ -f "$dir/run.env" ] && grep -Evq '^([A-Za-z_][A-Za-z0-9_]*=[A-Za-z0-9_./:,=+-]*|#.*|)$' "$dir/run.env"; then
  echo "run_piece: $dir/run.env: every line must be NAME=VALUE (letters, digits and _./:,=+- in the value) or a # comment"; exit 2
fi
# A folder too large for one call (slim_tree.sh --staging, then --staged) names in staged.sha256 the
# parts it left out of this call, which an earlier call on this machine staged in STAGED_DIR/NAME
# (experiments/stage_parts.sh; STAGED_DIR: .cache/staged, or what run_pieces.sh says). They go back
# into the folder (this disposable copy's) once their SHA-256 sums match; without them the piece runs
# nothing: a run without its cache compiles for most of a call, and one without its checkpoint's
# parts cannot resume.
if [ -f "$dir/staged.sha256" ]; then
  staged=${STAGED_DIR:-$PWD/.cache/staged}/$(basename "$dir")
  sums=$(cd "$dir" && pwd)/staged.sha256
  if ! [ -d "$staged" ] || ! (cd "$staged" && sha256sum --quiet --strict -c "$sums" >/dev/null 2>&1); then
    echo "run_piece: $dir's parts listed in staged.sha256 were left out of this call for copies staged on this machine by an earlier call (experiments/stage_parts.sh), and $staged $([ -d "$staged" ] && echo "does not hold them as listed" || echo "is not here"): nothing run (exit 8; the folder is unchanged)"
    exit 8
  fi
  while read -r _ p; do
    p=${p#\*}
    mkdir -p "$dir/$(dirname "$p")" && cp "$staged/$p" "$dir/$p" || { echo "run_piece: could not copy the staged $p into $dir"; exit 4; }
  done < "$dir/staged.sha256"
  echo "run_piece: $(wc -l < "$dir/staged.sha256") part(s) staged by an earlier call on this machine put back into $dir ($staged)"
fi
t0=$(date +%s)
args=$(cat "$dir/run.args")
run=$(echo "$args" | sed -n 's/.*--out \([^ ]*\).*/\1/p')
run=${run%/}
[ -n "$run" ] || { echo "run_piece: $dir/run.args lacks --out DIR"; exit 2; }
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
  export PYTHONPATH=$PWD:/tmp/site
fi
export PYTHONUNBUFFERED=1 SHED_JAX_CACHE=$PWD/.cache/device
[ -f "$dir/run.env" ] && set -a && . "$dir/run.env" && set +a
# AOT_PROBE=1: first the parts of the run's cache key that only this GPU host knows, into
# $OUT/aot_probe.json, so that a CPU host can compile the run's programs for it (experiments/aot_cache.py);
# where the carried cache served the host, the probe goes back at the end of run.log instead.
# AOT_GATE=1 probes too, and runs nothing (exit 6) when the carried cache holds no initial state under
# this host's key: its programs would compile again, which costs most of a call (SHED's chunk: 526 s).
probe=0 tool=
case ${AOT_GATE:-0} in 0|1) ;; *) echo "run_piece: AOT_GATE must be 0 or 1, got '$AOT_GATE'"; exit 2;; esac
if [ "${AOT_PROBE:-0}" = 1 ] || [ "${AOT_GATE:-0}" = 1 ]; then probe=1; fi
# this tree's aot_cache.py (the probe, and the portable keys' runner below) and shed_jax/profiling.py
# (its AOT_TRACE_CALL profile of a chunk), kept before the run's sources replace this tree's
if [ -f experiments/aot_cache.py ] || [ "$probe" = 1 ]; then
  tooldir=$(mktemp -d "${TMPDIR:-/tmp}/aot_cache.XXXXXX") || exit 4
  tool=$tooldir/aot_cache.py
  trap 'rm -rf "$tooldir"' EXIT  # the copy outlives the sources it came from, not the script
  cp experiments/aot_cache.py "$tool" || exit 4
  [ -f shed_jax/profiling.py ] && { cp shed_jax/profiling.py "$tooldir/" || exit 4; }
fi
# this host's GPU model (before the run's sources replace experiments/); RUN_PIECE_GPU= overrides it
gpu=${RUN_PIECE_GPU-$(bash experiments/gpu_model.sh 2>/dev/null)}
rm -rf shed_jax envs experiments && tar xzf "$dir/src.tgz" || exit 4
rm -f .source_commit  # the tree's commit (experiments/slim_tree.sh) does not describe the run's sources
# a warm machine keeps ignored paths between calls: another run's cache, or this run's directory as
# an earlier piece left it, would be packed with this piece's; it starts from the folder's parts alone
rm -rf .cache/device "$run"
mkdir -p runs .cache
if [ "$probe" = 1 ]; then
  python "$tool" probe "$dir/run.args" "$OUT/aot_probe.json" > "$OUT/aot_probe.log" 2>&1 || echo "run_piece: the probe failed (aot_probe.log)"
  tail -1 "$OUT/aot_probe.log"
fi
if ls "$dir"/ckpt.tgz.* >/dev/null 2>&1; then
  cat "$dir"/ckpt.tgz.* | tar xzf - || exit 5
  what="--resume $run"
else
  what=$args
fi
# A cache per GPU model: FOLDER/gpu-MODEL/cache.tgz.* (MODEL as gpu_model.sh names this host's GPU,
# e.g. h100; one filled on a CPU host by aot_fill.sh) serves this host in place of FOLDER/cache.tgz.*,
# which holds the programs compiled for the GPU the run began on. $OUT/gpu says which model ran.
cache=$dir
if [ -n "$gpu" ]; then
  echo "$gpu" > "$OUT/gpu"
  if ls "$dir/gpu-$gpu"/cache.tgz.* >/dev/null 2>&1; then cache=$dir/gpu-$gpu; echo "run_piece: the cache for $gpu ($cache)"; fi
fi
if ls "$cache"/cache.tgz.* >/dev/null 2>&1; then cat "$cache"/cache.tgz.* | tar xzf -; fi
# A cache filled with portable keys (aot_cache.py fill --portable: no part of the GPU host's driver or
# topology in them) serves every host with its GPU model; the run then files its programs the same way.
portable=0
if ls .cache/device/jax/*-portable-*-cache >/dev/null 2>&1; then
  [ -n "$tool" ] || { echo "run_piece: the carried cache holds portable keys, and this tree has no experiments/aot_cache.py to run with them"; exit 4; }
  portable=1; echo "run_piece: the carried cache holds portable keys: the run reads and files its GPU programs under them"
fi
probe_json=$OUT/aot_probe.json
served=0
probed_key() { python3 -c 'import json, sys; p = json.load(open(sys.argv[1]))["programs"]["jit_init_point"]; print(p["portable_key" if sys.argv[2] == "1" else "key"])' "$probe_json" "$portable" 2>/dev/null; }
if [ -f "$probe_json" ]; then  # does the carried cache serve this host?
  key=$(probed_key)
  if [ -n "$key" ] && [ -e ".cache/device/jax/$key-cache" ]; then echo "aot probe: the carried cache holds the initial state under this host's key"
    served=1
  elif [ "$what" != "$args" ] && ! ls .cache/device/jax/jit_init_point-*-cache >/dev/null 2>&1; then
    # a resume traces the initial state's shapes but never compiles it, so a folder may leave its entry
    # out of the cache to fit a call (shed-x on the 2-D walker, 2026-12-06): nothing to probe against;
    # under AOT_GATE=1 the chunk's own cache lookup below still stops a host the cache does not serve
    echo "aot probe: the carried cache holds no initial state under any key (a resume does not compile it): the chunk's lookup decides"
    served=1
  else
    echo "aot probe: the carried cache holds no initial state under this host's key ${key:0:40}: its programs will compile again"
    if [ "${AOT_GATE:-0}" = 1 ]; then echo "run_piece: AOT_GATE=1, so no run (the folder is unchanged; aot_probe.json says this host's key parts)"; exit 6; fi
  fi
  # where the run goes on, the probe's log and program text (only to diff a key that differs) go, and
  # its key parts go to the end of run.log once the run has ended: a call returns at most 8 files
  # (2026-12-06: these and the parts left out the run's log), and shed-x's checkpoint alone is four
  [ "$served" = 1 ] && rm -f "$OUT/aot_probe.log" "$OUT/aot_probe_init.mlir.gz"
fi
lim=$(( secs - ($(date +%s) - t0) - ${PACK_S:-45} ))
[ "$lim" -gt 0 ] || { echo "run_piece: SECONDS=$secs leaves no time to run after set-up and packing"; exit 2; }
# the run stops itself at lim and then writes its checkpoint (about 15-25 s); it is killed only if it
# has not exited 12 s before the packing must begin
# AOT_GATE=1 also stops the run as soon as its chunk proves not to be in the carried cache (the run's
# own line, or for sources older than that line JAX's "PERSISTENT COMPILATION CACHE MISS", which JAX
# logs at DEBUG level: JAX_DEBUG_LOG_MODULES shows that module's debug lines, and only while the jax
# logger's own level is above DEBUG, hence JAX_LOGGING_LEVEL; neither is part of any cache key):
# nothing is packed, the folder stays as it was (exit 7). Not JAX_EXPLAIN_CACHE_MISSES, which also
# logs that line: it turns on JAX 0.11's tracing-cache explainer too, which raises ValueError ("not
# enough values to unpack") inside a trace once Pallas' Triton lowering has cached a jaxpr (that call
# passes debug_info by keyword), and so failed the carried runs' early compile of their final evaluation
if [ "${AOT_GATE:-0}" = 1 ] && ! grep -qs "is not in the compilation cache" shed_jax/driver.py; then
  export JAX_LOGGING_LEVEL=WARNING JAX_DEBUG_LOG_MODULES=jax._src.compiler
fi
runner=(python -m shed_jax)
[ "$portable" = 1 ] && runner=(python "$tool" run -m shed_jax)
# a checkpoint every CHECKPOINT_EVERY s (120) besides the one at the stop: SHED's 34 MB state saved
# after every 11-s chunk held training up 14-21 s a piece (2026-12-06). The cost: a run killed before
# its stop's save is complete (the timeout below, 33 s after the stop) packs the newest complete
# checkpoint, which may now be up to CHECKPOINT_EVERY s old instead of one chunk
timeout -k 5 $(( lim + ${PACK_S:-45} - 12 )) "${runner[@]}" run $what --keep 1 --no-gif --checkpoint-every "$every" --time-limit $lim > "$OUT/run.log" 2>&1 &
pid=$!
missed=0
if [ "${AOT_GATE:-0}" = 1 ]; then
  while kill -0 "$pid" 2>/dev/null; do
    if grep -aqE "jit_chunk is not in the compilation cache|CACHE MISS for 'jit_chunk'" "$OUT/run.log"; then
      missed=1; kill -TERM "$pid"; break
    fi
    grep -aq "compiled in" "$OUT/run.log" && break
    sleep 2
  done
fi
wait "$pid"
rc=$?
if [ "$missed" = 1 ]; then
  echo "run_piece: AOT_GATE=1 and the chunk is not in the carried cache: the run was stopped before compiling it (the folder is unchanged; run.log says the key)"
  exit 7
fi
echo "rc $rc after $(( $(date +%s) - t0 )) s"
if [ -f "$probe_json" ]; then  # did the run itself compile (or find) the initial state under the probed key?
  key=$(probed_key)
  if [ -n "$key" ] && [ -e ".cache/device/jax/$key-cache" ]; then echo "aot probe: the run's initial state is in the cache under the probed key"
  else echo "aot probe: the cache holds no initial state under the probed key ${key:0:40}"; fi
fi
# Only the newest committed checkpoint goes back: one the run resumed from is deleted by the run
# only once its next save has finished in the background, which a stopped run may not reach.
newest=
if [ -d "$run/checkpoints" ]; then
  newest=$(for c in "$run"/checkpoints/*/commit_success.txt; do [ -f "$c" ] && basename "$(dirname "$c")"; done | grep -E '^[0-9]+$' | sort -n | tail -1)
  if [ -n "$newest" ]; then
    for c in "$run"/checkpoints/*; do [ "$(basename "$c")" = "$newest" ] || { rm -rf "$c"; echo "run_piece: left out checkpoint $(basename "$c"): the newest complete one is $newest"; }; done
  fi
fi
# the checkpoint in parts under the 16 MiB a call returns, written whole before it is put in $OUT.
# A run that goes on leaves its metrics.jsonl out: the checkpoint's metrics history holds the same
# records, and a resume writes the file again from it, byte for byte (shed-x's on the 2-D walker at
# budget step 216, 2026-12-06: 7.5 MB, 2.9 MB packed, growing with every piece, in a folder that
# must fit the 64 MiB a call carries). A finished run's results keep it.
if [ -d "$run" ]; then
  whole=${TMPDIR:-/tmp}/run_piece.$$.tgz
  keep=()
  [ "$rc" != 0 ] && [ -n "${newest:-}" ] && keep=(--exclude="$run/metrics.jsonl")
  tar czf "$whole" "${keep[@]}" "$run" && gzip -t "$whole" && split -b 15M "$whole" "$OUT/ckpt.tgz." || echo "no checkpoint packed"
  rm -f "$whole"
  ls -l "$OUT"/ckpt.tgz.*
fi
# Once the run has a checkpoint its programs are in the cache as executables, and XLA's kernel cache
# file (tens of MB under JAX_PERSISTENT_CACHE_ENABLE_XLA_CACHES=all) serves only compiles of new
# programs: it is left out, so the folder, the checkpoint and the wheels stay under what a call carries.
# A new program (e.g. the final evaluation's) then compiles its kernels again.
# A run that finished needs no cache: no piece reads it again, and three finished runs' caches beside
# their results would not fit one call's return (KEEP_CACHE=1 packs it anyway).
skip=()
[ -d "$run" ] && skip=(--exclude=xla_gpu_kernel_cache_file)
if [ "$rc" = 0 ] && [ "${KEEP_CACHE:-0}" != 1 ]; then
  echo "run_piece: the run finished, so its compilation cache is not packed (KEEP_CACHE=1 packs it)"
elif [ -d .cache/device ]; then tar czf - "${skip[@]}" .cache/device | split -b 15M - "$OUT/cache.tgz."; fi
last=$(tail -c 2000 "$OUT/run.log" | tr '\r' '\n' | grep -a -v '^ *$' | tail -4)
if [ "${served:-0}" = 1 ] && [ -f "$probe_json" ]; then
  { echo; echo "[run_piece] aot_probe.json, this host's key parts (the carried cache served them):"; cat "$probe_json"; } >> "$OUT/run.log"
  rm -f "$probe_json"
fi
echo "$last"
exit $rc
