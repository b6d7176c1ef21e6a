#!/bin/bash
# Takes what experiments/run_pieces.sh returned (FROM/pieces.tar.*) into each run's folder, as
# experiments/adopt_piece.sh does for one piece. Run from the repository root:
#   bash experiments/adopt_pieces.sh FROM FOLDER [FOLDER ...]
# The archive is checked whole before any folder is touched; a folder whose piece came back without a
# cache (it never ran) is left as it was, and the others are still taken. Each piece's run.log stays
# in a temporary folder (its path is printed), for the folder's pieceN.log.
set -u
usage="usage: bash experiments/adopt_pieces.sh FROM FOLDER [FOLDER ...]"
from=${1:?$usage}
shift
[ $# -ge 1 ] || { echo "$usage"; exit 2; }
ls "$from"/pieces.tar.* >/dev/null 2>&1 || { echo "adopt_pieces: $from holds no pieces.tar.*"; exit 2; }
for f in "$@"; do [ -f "${f%/}/run.args" ] || { echo "adopt_pieces: ${f%/} is not a carried run's folder (no run.args)"; exit 2; }; done
got=${TMPDIR:-/tmp}/adopt_pieces.$$
rm -rf "$got" && mkdir -p "$got"
cat "$from"/pieces.tar.* | tar xf - -C "$got" || { echo "adopt_pieces: $from/pieces.tar.* is not a whole archive; no folder touched"; rm -rf "$got"; exit 3; }
bad=0
for f in "$@"; do
  f=${f%/}
  n=$(basename "$f")
  echo "== $f (rc $(cat "$got/$n/rc" 2>/dev/null || echo '?'))"
  if [ ! -d "$got/$n" ]; then echo "adopt_pieces: the archive holds no piece for $n; $f left as it was"; bad=1; continue; fi
  bash "$(dirname "$0")/adopt_piece.sh" "$f" "$got/$n" || bad=1
  echo "its run.log: $got/$n/run.log"
done
exit $bad
