#!/bin/bash
# Takes what experiments/run_pieces.sh returned (FROM/NAME.tar.*, one archive per piece, NAME the
# folder's base name) into each run's folder, as experiments/adopt_piece.sh does for one piece. Run
# from the repository root:
#   bash experiments/adopt_pieces.sh FROM FOLDER [FOLDER ...]
# A piece whose archive is missing or not whole leaves its folder as it was; the others are still
# taken. Each piece's run.log is kept (its path is printed), for the folder's pieceN.log; the rest of
# what was unpacked is removed. Exit 0 when every folder took its piece, else 1; 2 bad arguments.
set -u
set -o pipefail
usage="usage: bash experiments/adopt_pieces.sh FROM FOLDER [FOLDER ...]"
from=${1:?$usage}
shift
[ $# -ge 1 ] || { echo "$usage"; exit 2; }
for f in "$@"; do [ -f "${f%/}/run.args" ] || { echo "adopt_pieces: ${f%/} is not a carried run's folder (no run.args)"; exit 2; }; done
got=${TMPDIR:-/tmp}/adopt_pieces.$$
mkdir -p "$got"
bad=0
for f in "$@"; do
  f=${f%/}
  n=$(basename "$f")
  echo "== $f"
  if ! ls "$from/$n".tar.* >/dev/null 2>&1; then echo "adopt_pieces: $from holds no $n.tar.*; $f left as it was"; bad=1; continue; fi
  # run_pieces.sh packs NAME.whole last: without it the archive was cut short (tar itself may not say so)
  rm -f "$got/$n.whole"
  if ! cat "$from/$n".tar.* | tar xf - -C "$got" 2>/dev/null || [ ! -f "$got/$n.whole" ]; then
    echo "adopt_pieces: $from/$n.tar.* is not a whole archive; $f left as it was"; rm -rf "${got:?}/$n"; bad=1; continue
  fi
  echo "its exit code: $(cat "$got/$n/rc" 2>/dev/null || echo '?')"
  bash "$(dirname "$0")/adopt_piece.sh" "$f" "$got/$n" || bad=1
  if [ -f "$got/$n/run.log" ]; then mv "$got/$n/run.log" "$got/$n.run.log" && echo "its run.log: $got/$n.run.log"; fi
  rm -rf "${got:?}/$n" "$got/$n.whole"
done
exit $bad
