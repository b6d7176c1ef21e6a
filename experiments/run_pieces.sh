#!/bin/bash
# Several carried runs' pieces in one device call, side by side on its one GPU: each is
# experiments/run_piece.sh on its own copy of the tree (run_piece.sh puts a run's sources in place of
# the tree's, so two runs cannot share one), seen at the tree's own path through a private mount
# (unshare -m; the compilation cache's keys hold the sources' and the cache's absolute paths, so a
# copy elsewhere would miss every carried program), with its share of the GPU's memory. At 200
# walkers a 2-D walker step is mostly small kernels (docs/bipedal.md, "Where the launches are"),
# which was expected to leave the GPU idle between them for a second run to fill; it does not (each
# of two runs got about half the GPU, 2026-12-06), and a trace found one run's GPU busy 92 % of the
# time (docs/log/benchmarks.md, 2026-12-07). What a call of this still saves is a machine start.
# Run from the repository root, as root, on the device machine (a disposable copy: OUT must be set):
#   OUT=DIR bash experiments/run_pieces.sh SECONDS FOLDER [FOLDER ...]
# SECONDS counts from this script's start, its set-up included, as run_piece.sh's does: give the
# call's limit less about 30 s. Each piece returns run_piece.sh's files as one archive of its own in
# 15 MiB parts, $OUT/NAME.tar.* (NAME: the folder's base name), so that a part left out of the
# call's return loses one piece, not both (a call returns at most 8 files and 64 MiB). Take them with
#   bash experiments/adopt_pieces.sh FROM FOLDER [FOLDER ...]
# Environment: AOT_GATE, CHECKPOINT_EVERY and PACK_S go to every piece; MEM_FRACTION (default 0.9
# over the number of pieces) becomes each piece's XLA_PYTHON_CLIENT_MEM_FRACTION. Where the pieces'
# files would not fit a call's return, their caches are left out, largest first (below). Exit: 0 when every
# piece exited 0 or 75 (stopped at its time limit and saved) and what they return fits a call's
# return; 1 otherwise (each piece's code is printed); 2 bad arguments; 5 no private mounts here.
set -u
set -o pipefail
usage="usage: OUT=DIR bash experiments/run_pieces.sh SECONDS FOLDER [FOLDER ...]"
t0=$(date +%s)
secs=${1:?$usage}
shift
[ $# -ge 1 ] || { echo "$usage"; exit 2; }
case $secs in ''|*[!0-9]*) echo "run_pieces: SECONDS must be a whole number, got '$secs'"; exit 2;; esac
: "${OUT:?run_pieces.sh runs on a disposable copy of the tree: set OUT}"
folders=() names=()
for f in "$@"; do
  f=${f#./}
  f=${f%/}
  case $f in /*|../*) echo "run_pieces: FOLDER must be a path inside the tree, got '$f'"; exit 2;; esac
  [ -f "$f/run.args" ] && [ -f "$f/src.tgz" ] || { echo "run_pieces: $f is not a carried run's folder (run.args and src.tgz)"; exit 2; }
  n=$(basename "$f")
  case " ${names[*]-} " in *" $n "*) echo "run_pieces: two folders named $n"; exit 2;; esac
  folders+=("$f") names+=("$n")
done
frac=${MEM_FRACTION:-$(python3 -c "import sys; print(round(0.9 / int(sys.argv[1]), 3))" $#)}
python3 -c "import sys; f = float(sys.argv[1]); sys.exit(not 0 < f * int(sys.argv[2]) <= 1)" "$frac" $# 2>/dev/null || {
  echo "run_pieces: MEM_FRACTION=$frac for $# pieces does not fit in one GPU (their sum must be at most 1)"; exit 2; }
root=$PWD
work=${TMPDIR:-/tmp}/run_pieces.$$
case $work/ in "$root"/*) echo "run_pieces: TMPDIR is inside the tree; set it elsewhere"; exit 2;; esac
rm -rf "$work" && mkdir -p "$work/probe"
# each piece sees its copy at the tree's path: a private mount namespace per piece, which needs root
if ! unshare -m --propagation private bash -c 'mount --bind "$0" "$1"' "$work/probe" "$root" 2>"$work/why"; then
  echo "run_pieces: this machine gives no private mounts ($(head -c 200 "$work/why" | tr '\n' ' ')), so the pieces cannot each see their sources at $root; run them one at a time with run_piece.sh"
  rm -rf "$work"; exit 5
fi
# the wheels once, here: pieces that each installed them into one --target at the same time would race
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
fi
# parts an earlier call staged on this machine (stage_parts.sh) are in .cache/staged, which each
# piece's private mount hides: they are read from a copy beside the pieces' trees
staged_env=()
if [ -d .cache/staged ]; then
  cp -a .cache/staged "$work/staged" || exit 4
  staged_env=(STAGED_DIR="$work/staged")
fi
pids=()
for i in "${!folders[@]}"; do
  f=${folders[$i]} n=${names[$i]}
  tree=$work/tree.$n out=$work/out/$n
  mkdir -p "$tree" "$out"
  # the tree without the other pieces' folders, the wheels (installed above), runs, caches and what is aside
  others=()
  for g in "${folders[@]}"; do [ "$g" = "$f" ] || others+=(--exclude="./$g"); done
  tar cf - --exclude=./.whl --exclude=./.cache --exclude=./runs --exclude=./.git --exclude=./.aside "${others[@]}" . \
    | tar xf - -C "$tree" || exit 4
  left=$(( secs - ($(date +%s) - t0) ))
  unshare -m --propagation private env OUT="$out" PYTHONPATH="$root:/tmp/site" XLA_PYTHON_CLIENT_MEM_FRACTION="$frac" "${staged_env[@]}" \
    bash -c 'mount --bind "$0" "$1" && cd "$1" && bash experiments/run_piece.sh "$2" "$3" > "$OUT/piece.out" 2>&1; echo $? > "$OUT/rc"' \
    "$tree" "$root" "$f" "$left" &
  pids+=($!)
  echo "run_pieces: $n started with $left s (its copy seen at $root, XLA_PYTHON_CLIENT_MEM_FRACTION=$frac)"
done
wait "${pids[@]}"
bad=0
# What comes back must fit a call's return (64 MiB; RETURN_BYTES for tests). Where it would not, the
# pieces' caches are left out, largest first, before any checkpoint is lost: a folder keeps the cache
# it had (its next piece then traces the chunk again instead of reading a new stand-in), while a
# piece whose archive does not come back whole loses its steps (PLR⊥'s on 2026-12-06).
limit=${RETURN_BYTES:-$(( 64 * 1024 * 1024 ))}
case $limit in ''|*[!0-9]*) echo "run_pieces: RETURN_BYTES must be a whole number of bytes, got '$limit'"; limit=$(( 64 * 1024 * 1024 ));; esac
returned() { cat "$work"/out/*/* 2>/dev/null | wc -c; }
margin=$(( 16384 * ${#names[@]} ))  # tar's headers and padding
if [ $(( $(returned) + margin )) -gt "$limit" ]; then
  for n in $(for n in "${names[@]}"; do echo "$(cat "$work/out/$n"/cache.tgz.* 2>/dev/null | wc -c) $n"; done | sort -rn | awk '$1 > 0 {print $2}'); do
    [ $(( $(returned) + margin )) -gt "$limit" ] || break
    b=$(cat "$work/out/$n"/cache.tgz.* | wc -c)
    rm -f "$work/out/$n"/cache.tgz.*
    echo "run_pieces: left out $n's cache ($b bytes) so that the pieces' checkpoints come back within a call's return; its folder keeps the cache it had"
  done
fi
for n in "${names[@]}"; do
  rc=$(cat "$work/out/$n/rc" 2>/dev/null || echo "?")
  echo "== $n: rc $rc"
  tail -n 6 "$work/out/$n/piece.out" 2>/dev/null
  case $rc in 0|75) ;; *) bad=1;; esac
  # NAME.whole last: tar takes an archive cut at a header's edge for a shorter whole one, so
  # adopt_pieces.sh believes an archive whose last member it finds
  touch "$work/out/$n.whole"
  (cd "$work/out" && tar cf - "$n" "$n.whole") | split -b 15M - "$OUT/$n.tar." \
    || { echo "run_pieces: packing $n failed"; bad=1; }
done
ls -l "$OUT"/*.tar.*
parts=$(ls "$OUT" | wc -l)
bytes=$(cat "$OUT"/* | wc -c)
if [ "$parts" -gt 8 ] || [ "$bytes" -gt "$limit" ]; then
  echo "run_pieces: $parts files, $bytes bytes: more than a call returns (8 files, 64 MiB); some pieces will not come back whole"
  bad=1
fi
rm -rf "$work"
exit $bad
