#!/bin/bash
# The first of a piece's two calls, for a carried run's folder whose parts (checkpoint and compilation
# cache) are together over what one call carries (experiments/slim_tree.sh --staging, then --staged):
# on the device machine, copies every archive part the folder holds in this call (FOLDER/**/*.tgz.*:
# its cache for the call's GPU model and the checkpoint's first part) to .cache/staged/NAME/, under
# the same relative paths (NAME: the folder's base name). .cache/ is ignored, so the warm machine
# keeps the copy until the next call, whose run_piece.sh (or run_pieces.sh) puts the parts listed in
# FOLDER/staged.sha256 back into the folder once their SHA-256 sums match. Run from the repository root:
#   bash experiments/stage_parts.sh FOLDER [FOLDER ...]
# Exit 0 when every folder's parts were staged; 1 a copy failed; 2 bad arguments (nothing staged).
set -u
usage="usage: bash experiments/stage_parts.sh FOLDER [FOLDER ...]"
[ $# -ge 1 ] || { echo "$usage"; exit 2; }
names=" "
for f in "$@"; do
  f=${f%/}
  [ -f "$f/run.args" ] || { echo "stage_parts: $f is not a carried run's folder (no run.args)"; exit 2; }
  case $names in *" $(basename "$f") "*) echo "stage_parts: two folders named $(basename "$f") (each is staged under its name)"; exit 2;; esac
  names="$names$(basename "$f") "
  [ -n "$(find "$f" -name '*.tgz.*' -type f | head -1)" ] || { echo "stage_parts: $f holds no archive parts in this call"; exit 2; }
done
for f in "$@"; do
  f=${f%/}
  to=.cache/staged/$(basename "$f")
  rm -rf "$to" && mkdir -p "$to" || exit 1
  (cd "$f" && find . -name '*.tgz.*' -type f | sed 's|^\./||' | sort) > "$to.list"
  while read -r p; do
    mkdir -p "$to/$(dirname "$p")" && cp "$f/$p" "$to/$p" || { echo "stage_parts: could not copy $f/$p to $to"; exit 1; }
  done < "$to.list"
  echo "stage_parts: $(basename "$f"): $(wc -l < "$to.list") part(s), $(find "$to" -type f -print0 | du -cb --files0-from=- | tail -1 | cut -f1) bytes, staged in $to: $(tr '\n' ' ' < "$to.list")"
  rm -f "$to.list"
done
exit 0
