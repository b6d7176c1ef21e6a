#!/bin/bash
# Keep a device call's carried tree under its 64 MiB: everything under docs/ but the carried runs'
# folders (one, or several for experiments/run_pieces.sh), and tests/ (a run needs none of it), go to .aside/ (git-ignored, so not carried; it stays in
# the checkout). With --bipedal-wheels, .whl/ keeps what a 2-D walker run needs: MuJoCo's 9.7 MB
# compiled wheel and Brax's own dependencies (trimesh, jaxopt, ml_collections, tensorboardX: 1.1 MB)
# go aside, as the 2-D walker imports neither MuJoCo nor Brax; the mujoco, mujoco_mjx and brax wheels
# stay, because `python -m shed_jax` checks that they are installed, mujoco_mjx's without its 6.5 MB
# of test data.
# With --gpu MODEL (a call that names its kind, e.g. nvidia-h100-x1 -> h100), the folder's caches for
# other GPU models go aside too: FOLDER/cache.tgz.* when FOLDER/gpu-MODEL/ exists, and other gpu-*/.
# A folder whose checkpoint and cache together are over what a call carries (shed-x on the 2-D walker:
# 51 MB and 12 MB, 2026-12-06) goes in two calls on one warm machine. The first (--staging) carries
# its cache for MODEL and the checkpoint's first part, the other parts aside, and copies them onto the
# machine with experiments/stage_parts.sh; the second (--staged), started before the machine's idle
# release (30 s), carries the rest, those parts aside and their SHA-256 sums in FOLDER/staged.sha256,
# by which run_piece.sh finds the staged copies, checks them and puts them back. Both need --gpu.
# Run from the repository root:
#   bash experiments/slim_tree.sh [--bipedal-wheels] [--gpu MODEL] [--staging | --staged] FOLDER [FOLDER ...]
#   bash experiments/slim_tree.sh --restore                   # after the call(s), before or after adopt_piece.sh
# docs/ must have no uncommitted changes outside FOLDER, so that nothing but moves happens. Commit the
# piece after --restore (`git add FOLDER`, never `git commit -a` or `git add -A`): while the tree is
# slim, git sees the rest of docs/, tests/ and the folder's caches for other GPU models as deleted
# (and the suite cannot run).
set -u
usage="usage: bash experiments/slim_tree.sh [--bipedal-wheels] [--gpu MODEL] [--staging | --staged] FOLDER [FOLDER ...] | --restore"
aside=.aside
size() { bash "$(dirname "$0")/carried_size.sh"; }  # what a call carries, with the wheels
git rev-parse --git-dir >/dev/null 2>&1 && [ -d docs ] || { echo "slim_tree: run it from the repository root"; exit 2; }
grep -qx "/$aside/" .git/info/exclude 2>/dev/null || echo "/$aside/" >> .git/info/exclude
if [ "${1:-}" = --restore ]; then
  find docs/results -name staged.sha256 -type f -delete 2>/dev/null  # written by --staged for one call
  rm -f .source_commit  # written by the slim for the call
  [ -d "$aside" ] || { echo "slim_tree: nothing is aside"; exit 0; }
  # docs/ back; the carried folder's entries set aside (its caches for other GPU models) back into it.
  # Nothing in the tree is overwritten: an entry there already (a part the piece replaced) wins, and
  # a split archive's parts (NAME.tgz.aa, .ab, ...) go back only if the tree holds none of that set,
  # or only copies of the set's own parts (--staging and --staged leave some parts in the tree and
  # the whole set aside). In a folder of a staged piece (.aside/split), a set whose parts in the tree
  # differ (the piece's, adopted before the restore) replaces the set-aside one, which is dropped: it
  # is the folder's committed state, in git.
  split_folders=$(cat "$aside/split" 2>/dev/null)
  rm -f "$aside/split"
  shopt -s dotglob
  back() {  # FROM TO
    local p q set mine
    if [ -d "$1" ] && [ -d "$2" ]; then
      for p in "$1"/*; do [ -e "$p" ] && back "$p" "$2/$(basename "$p")"; done
      return
    fi
    case $(basename "$1") in
      *.tgz.??) set=$(basename "$1" | sed 's/\.tgz\...$/.tgz./')  # the whole set moves, or none of it
        mine=1
        for q in "$(dirname "$2")/$set"*; do
          [ -e "$q" ] || continue
          cmp -s "$q" "$(dirname "$1")/$(basename "$q")" || { mine=0; break; }
        done
        if [ "$mine" = 1 ]; then mv -f "$(dirname "$1")/$set"* "$(dirname "$2")/"; return; fi
        for f in $split_folders; do
          case ${2#./} in "$f"/*)
            rm -f "$(dirname "$1")/$set"*
            echo "slim_tree: $(dirname "${2#./}")/$set* in the tree replace the set-aside ones (the folder's committed parts, in git)"; return;;
          esac
        done
        echo "slim_tree: $(dirname "${2#./}") holds other parts of $set*; its set-aside parts left in $aside";;
      *) if [ -e "$2" ]; then echo "slim_tree: ${2#./} exists in the tree too; left in $aside"; else mv "$1" "$2"; fi;;
    esac
  }
  [ -d "$aside/docs" ] && back "$aside/docs" docs
  if [ -d "$aside/tests" ]; then if [ -e tests ]; then back "$aside/tests" tests; else mv "$aside/tests" tests; fi; fi
  [ -d "$aside/whl" ] && mkdir -p .whl && mv "$aside"/whl/* .whl/ 2>/dev/null
  find "$aside" -depth -type d -empty -delete 2>/dev/null
  [ -d "$aside" ] && echo "slim_tree: $aside still holds: $(find "$aside" -type f | head -3 | tr '\n' ' ')" && exit 1
  echo "slim_tree: restored; the tree carries $(size) bytes with the wheels"
  exit 0
fi
core=0 gpu= split=
while [ $# -gt 0 ]; do
  case $1 in
    --bipedal-wheels) core=1; shift;;
    --staging|--staged) [ -z "$split" ] || [ "$split" = "$1" ] || { echo "slim_tree: --staging and --staged are the two calls of one piece: give one"; exit 2; }
      split=$1; shift;;
    --gpu) [ $# -ge 2 ] || { echo "slim_tree: --gpu takes a GPU model (h100, h200, a100)"; exit 2; }; gpu=$2; shift 2;;
    *) break;;
  esac
done
case $gpu in ''|h100|h200|a100) ;; *) echo "slim_tree: --gpu takes a model as experiments/gpu_model.sh names it (h100, h200, a100), got '$gpu'"; exit 2;; esac
[ $# -ge 1 ] || { echo "$usage"; exit 2; }
[ -z "$split" ] || [ -n "$gpu" ] || { echo "slim_tree: $split needs --gpu MODEL (the model whose cache is staged)"; exit 2; }
folders=()
for folder in "$@"; do
  folder=${folder%/}
  case $folder in docs/results/?*) ;; *) echo "slim_tree: FOLDER must be a folder under docs/results/, got '$folder'"; exit 2;; esac
  [ -d "$folder" ] || { echo "slim_tree: no folder $folder"; exit 2; }
  folders+=("$folder")
done
[ -e "$aside" ] && { echo "slim_tree: $aside exists: restore first (bash experiments/slim_tree.sh --restore)"; exit 2; }
excl=()
for folder in "${folders[@]}"; do excl+=(":(exclude)$folder"); done
dirty=$(git status --porcelain -- docs "${excl[@]}" | head -3)
[ -z "$dirty" ] || { echo "slim_tree: docs/ has uncommitted changes outside ${folders[*]} (commit them first): $(echo "$dirty" | tr '\n' ' ')"; exit 2; }
kept() { local f; for f in "${folders[@]}"; do [ "$1" = "$f" ] && return 0; done; return 1; }
# the commit the call's records name (shed_jax.runtime.source_commit): the device's copy of the tree
# may carry older git metadata; untracked and not ignored, the file travels with the call
git describe --always --dirty > .source_commit
mkdir -p "$aside/docs/results"
for p in docs/*; do [ "$p" = docs/results ] || mv "$p" "$aside/docs/"; done
for p in docs/results/*; do kept "$p" || mv "$p" "$aside/docs/results/"; done
[ -d tests ] && mv tests "$aside/tests"
if [ -n "$gpu" ]; then  # the folders' caches for other GPU models (restored with each folder's own path)
  for folder in "${folders[@]}"; do
    keep=$aside/$folder
    for p in "$folder"/gpu-*; do
      [ -d "$p" ] && [ "$p" != "$folder/gpu-$gpu" ] && mkdir -p "$keep" && mv "$p" "$keep/"
    done
    if ls "$folder/gpu-$gpu"/cache.tgz.* >/dev/null 2>&1; then for p in "$folder"/cache.tgz.*; do [ -e "$p" ] && mkdir -p "$keep" && mv "$p" "$keep/"; done; fi
  done
fi
# the parts staged in the first call of a staged piece: the cache for MODEL (gpu-MODEL's, else the
# folder's own) and the checkpoint's first part
staged_parts() {  # FOLDER -> relative paths
  local c=gpu-$gpu
  ls "$1/$c"/cache.tgz.* >/dev/null 2>&1 || c=.
  (cd "$1/$c" && ls cache.tgz.* 2>/dev/null) | sed "s|^|$c/|; s|^\./||"
  [ -f "$1/ckpt.tgz.aa" ] && echo ckpt.tgz.aa
}
[ -n "$split" ] && printf '%s\n' "${folders[@]}" > "$aside/split"
for folder in "${folders[@]}"; do
  [ -n "$split" ] || break
  parts=$(staged_parts "$folder")
  echo "$parts" | grep -q '^ckpt' && echo "$parts" | grep -q cache.tgz || {
    echo "slim_tree: $split: $folder needs a checkpoint and a cache for $gpu to split between two calls"; bash "$0" --restore >/dev/null; exit 2; }
  keep=$aside/$folder
  if [ "$split" = --staging ]; then  # the checkpoint's other parts wait for the second call
    mkdir -p "$keep" && cp -p "$folder/ckpt.tgz.aa" "$keep/"  # the whole set aside, for --restore
    for p in "$folder"/ckpt.tgz.*; do [ "$p" = "$folder/ckpt.tgz.aa" ] || mv "$p" "$keep/"; done
  else
    (cd "$folder" && sha256sum $parts) > "$folder/staged.sha256"
    mkdir -p "$keep" && for p in "$folder"/ckpt.tgz.*; do cp -p "$p" "$keep/"; done  # the whole set aside, for --restore
    for p in $parts; do mkdir -p "$keep/$(dirname "$p")" && mv "$folder/$p" "$keep/$(dirname "$p")/"; done
  fi
done
if [ "$core" = 1 ]; then
  for w in .whl/mujoco_core-*.whl .whl/trimesh-*.whl .whl/jaxopt-*.whl .whl/ml_collections-*.whl .whl/tensorboardx-*.whl; do
    [ -f "$w" ] && mkdir -p "$aside/whl" && mv "$w" "$aside/whl/"
  done
  # and MJX's wheel goes aside for a copy without its 6.5 MB of test data (mujoco/mjx/test_data/ and
  # their RECORD lines): the package still installs and is found, and --restore moves the original
  # back over the copy
  for w in .whl/mujoco_mjx-*.whl; do
    [ -f "$w" ] || continue
    mkdir -p "$aside/whl" && mv "$w" "$aside/whl/" || exit 1
    python3 - "$aside/whl/$(basename "$w")" "$w" <<'PY' || { mv "$aside/whl/$(basename "$w")" "$w"; echo "slim_tree: could not copy $w without its test data"; exit 1; }
import sys, zipfile
skip = "mujoco/mjx/test_data/"
with zipfile.ZipFile(sys.argv[1]) as src, zipfile.ZipFile(sys.argv[2], "w", zipfile.ZIP_DEFLATED) as dst:
    for info in src.infolist():
        if info.filename.startswith(skip):
            continue
        data = src.read(info)
        if info.filename.endswith(".dist-info/RECORD"):
            data = b"".join(l for l in data.splitlines(True) if not l.startswith(skip.encode()))
        dst.writestr(info, data)
PY
  done
fi
total=$(size)
echo "slim_tree: docs/ holds only ${folders[*]}; the tree carries $total bytes with the wheels (limit $(( 64 * 1024 * 1024 )))"
[ "$total" -le $(( 64 * 1024 * 1024 )) ] || { echo "slim_tree: still over the 64 MiB a call carries"; exit 1; }
exit 0
