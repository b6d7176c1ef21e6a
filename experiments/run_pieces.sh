#!/bin/bash
# Several carried runs' pieces in one device call, side by side on its one GPU: each is
# experiments/run_piece.sh on its own copy of the tree (run_piece.sh puts a run's sources in place of
# the tree's, so two runs cannot share one), with its share of the GPU's memory. At 200 walkers a 2-D
# walker step is mostly kernel launches (docs/bipedal.md, "Where the launches are"), so one run leaves
# the GPU idle between them; whether a second run fills those gaps is what a call of this measures.
# Run from the repository root, on the device machine (a disposable copy: OUT must be set):
#   OUT=DIR bash experiments/run_pieces.sh SECONDS FOLDER [FOLDER ...]
# SECONDS is each piece's, as run_piece.sh takes it, and so the call's less about 20 s: the pieces run
# at the same time and are packed together after. What the pieces return (run_piece.sh's files, under
# a folder named after each FOLDER) comes back as one archive in 15 MiB parts, $OUT/pieces.tar.*
# (a call returns at most 8 files: two pieces return 14). Take it with
#   bash experiments/adopt_pieces.sh FROM FOLDER [FOLDER ...]
# Environment: AOT_GATE, CHECKPOINT_EVERY and PACK_S go to every piece; MEM_FRACTION (default 0.9
# over the number of pieces) becomes each piece's XLA_PYTHON_CLIENT_MEM_FRACTION. Exit: 0 when every
# piece exited 0 or 75 (stopped at its time limit and saved), else 1; each piece's code is printed.
set -u
usage="usage: OUT=DIR bash experiments/run_pieces.sh SECONDS FOLDER [FOLDER ...]"
secs=${1:?$usage}
shift
[ $# -ge 1 ] || { echo "$usage"; exit 2; }
case $secs in ''|*[!0-9]*) echo "run_pieces: SECONDS must be a whole number, got '$secs'"; exit 2;; esac
: "${OUT:?run_pieces.sh runs on a disposable copy of the tree: set OUT}"
names=()
for f in "$@"; do
  f=${f%/}
  [ -f "$f/run.args" ] && [ -f "$f/src.tgz" ] || { echo "run_pieces: $f is not a carried run's folder (run.args and src.tgz)"; exit 2; }
  n=$(basename "$f")
  case " ${names[*]-} " in *" $n "*) echo "run_pieces: two folders named $n"; exit 2;; esac
  names+=("$n")
done
frac=${MEM_FRACTION:-$(python3 -c "import sys; print(round(0.9 / int(sys.argv[1]), 3))" $#)}
python3 -c "import sys; f = float(sys.argv[1]); sys.exit(not 0 < f * int(sys.argv[2]) <= 1)" "$frac" $# 2>/dev/null || {
  echo "run_pieces: MEM_FRACTION=$frac for $# pieces does not fit in one GPU (their sum must be at most 1)"; exit 2; }
# the wheels once, here: pieces that each installed them into one --target at the same time would race
if ls .whl/*.whl >/dev/null 2>&1; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 3
fi
work=${TMPDIR:-/tmp}/run_pieces.$$
rm -rf "$work" && mkdir -p "$work"
pids=()
for f in "$@"; do
  f=${f%/}
  n=$(basename "$f")
  tree=$work/tree.$n out=$work/out/$n
  mkdir -p "$tree" "$out"
  # the tree without the other pieces' folders, the wheels (installed above), runs and caches
  others=()
  for g in "$@"; do g=${g%/}; [ "$g" = "$f" ] || others+=(--exclude="./$g"); done
  tar cf - --exclude=./.whl --exclude=./.cache --exclude=./runs --exclude=./.git "${others[@]}" . | tar xf - -C "$tree" || exit 4
  # the copy's sources first on the path: aot_cache.py runs from /tmp, where the path decides the package
  (cd "$tree" && OUT=$out PYTHONPATH=$tree:/tmp/site XLA_PYTHON_CLIENT_MEM_FRACTION=$frac \
     bash experiments/run_piece.sh "$f" "$secs" > "$out/piece.out" 2>&1; echo $? > "$out/rc") &
  pids+=($!)
  echo "run_pieces: $n started (tree $tree, XLA_PYTHON_CLIENT_MEM_FRACTION=$frac)"
done
wait "${pids[@]}"
bad=0
for n in "${names[@]}"; do
  rc=$(cat "$work/out/$n/rc" 2>/dev/null || echo "?")
  echo "== $n: rc $rc"
  tail -n 6 "$work/out/$n/piece.out"
  case $rc in 0|75) ;; *) bad=1;; esac
done
(cd "$work/out" && tar cf - "${names[@]}") | split -b 15M - "$OUT/pieces.tar." || { echo "run_pieces: packing failed"; exit 4; }
ls -l "$OUT"/pieces.tar.*
n_parts=$(ls "$OUT"/pieces.tar.* | wc -l)
[ "$n_parts" -le 8 ] || echo "run_pieces: $n_parts parts, more than the 8 files a call returns: run fewer pieces together"
rm -rf "$work"
exit $bad
