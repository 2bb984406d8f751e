#!/bin/bash
# Can the network learn futures it is trained on? Trains fresh networks with PyTorch on a GPU
# machine, side by side, each on a small set of scenes, then asks each to give back its own
# training windows (`lanes.py`: unguided samples against the recorded futures, and one
# denoising step from the recorded future plus noise of each level). README.md beside this
# file, "Does the network learn its own windows?".
#
# It expects, in the folder named by PACK (default .dev, relative to the repository root):
#   ds.xz           an x86-64 `drivescript` built here (`strip`, then `xz -9`)
#   sets.tar.xz     one folder of scene files per training set (their names are the sets')
# and trains, for M minutes each, one network per line of RUNS ("NAME EXPORT TRAIN.PY-FLAGS..."),
# evaluating each on its own export's training windows, beside the checkpoint the export was
# encoded with (COMPARE=0: without it). Each line of EXPORTS ("EXPORT SET CHECKPOINT") encodes a
# set as that checkpoint's network reads it (a route-frame checkpoint: futures told against
# lane routes); without EXPORTS, every set is encoded with FROM and the export takes its name.
# env: OUT, M (minutes), RUNS, EXPORTS, FROM (data/cities-wip), BATCH (256), SPLIT (noise
# levels), COMPARE (1), LANES_FLAGS (lanes.py's, default --windows 64 --from-log).
set -u
cd "$(dirname "$0")/../.."
T0=$(date +%s)
PY=${PY:-python3}
PACK=${PACK:-.dev}
FROM=${FROM:-data/cities-wip}
SPLIT=${SPLIT:-0.05 0.3 1 3 10 30 80}
log() { echo "[$(( $(date +%s) - T0 )) s] $*"; }
export PYTHONUNBUFFERED=1
nvidia-smi -L 2>&1 | head -2
$PY benches/torch/unpack.py "$PACK" sets.tar.xz /tmp/sets || exit 1
log extracted
if [ -z "${EXPORTS:-}" ]; then
  EXPORTS=$(for s in $(ls /tmp/sets); do echo "$s $s $FROM"; done)
fi
declare -A CHECK
while read -r name set from; do
  [ -z "$name" ] && continue
  CHECK[$name]=$from
  rm -rf /tmp/e_$name
  /tmp/ds train --export /tmp/e_$name --resume "$from" --urban /tmp/sets/$set 2>&1 \
    | grep -v "scenes read\|files written" &
done <<< "$EXPORTS"
wait
log exported
rm -rf /tmp/logs; mkdir -p /tmp/logs
while read -r name set flags; do
  [ -z "$name" ] && continue
  $PY benches/torch/train.py /tmp/e_$set /tmp/r_$name --minutes $M --batch ${BATCH:-256} \
    --eval-every 20 $flags > /tmp/logs/$name.train.log 2>&1 &
done <<< "$RUNS"
sleep 60
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv 2>&1
wait
log trained
for f in /tmp/logs/*.train.log; do echo "== $f"; cat $f; done > $OUT/train.log
grep -h "done:" /tmp/logs/*.train.log
tar cf $OUT/checkpoints.tar -C /tmp $(cd /tmp && ls -d r_*/last)
# The evaluations run on the CPU (lanes.py's sampler is the port's, on CPU tensors), side by side.
while read -r name set flags; do
  [ -z "$name" ] && continue
  compare=${CHECK[$set]}
  [ "${COMPARE:-1}" = 0 ] && compare=
  OMP_NUM_THREADS=3 $PY benches/torch/lanes.py /tmp/e_$set /tmp/r_$name/last $compare \
    --file train-00000.safetensors ${LANES_FLAGS:---windows 64 --from-log} --split $SPLIT \
    > /tmp/logs/$name.lanes.log 2>&1 &
done <<< "$RUNS"
wait
log evaluated
for f in /tmp/logs/*.lanes.log; do echo "== $f"; cat $f; done | tee $OUT/lanes.log
