#!/bin/bash
# call 2: the lander before (888dc48) and after (sincos, FMA) in turn, twice; the new without FMA; latency at 80/400
set -u
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
mkdir -p /tmp/old && tar xzf runs/old_src.tgz -C /tmp/old
old() { (cd /tmp/old && PYTHONPATH=/tmp/old:/tmp/site timeout 120 python -m experiments.$1 "${@:2}" 2>&1 | grep -v Warn | tail -${TAILN:-2}); }
new() { PYTHONPATH=$PWD:/tmp/site timeout 120 python -m experiments.$1 "${@:2}" 2>&1 | grep -v Warn | tail -${TAILN:-2}; }
for r in 1 2; do
  mkdir -p $OUT/lo$r $OUT/ln$r $OUT/lnf$r
  echo "== old $r"; old bench_lander --batches 131072 --gym-seconds 0 --out $OUT/lo$r
  echo "== new $r"; new bench_lander --batches 131072 --gym-seconds 0 --out $OUT/ln$r
  echo "== new, no FMA $r"; XLA_FLAGS=--xla_backend_extra_options=-nvptx-fma-level=0 new bench_lander --batches 131072 --gym-seconds 0 --out $OUT/lnf$r
done
mkdir -p $OUT/lato $OUT/latn
echo "== latency old"; TAILN=3 old bench_latency --batches 80,400 --steps 200 --skip-student --out $OUT/lato
echo "== latency new"; TAILN=3 new bench_latency --batches 80,400 --steps 200 --skip-student --out $OUT/latn
