#!/bin/bash
# Trains the cities network with PyTorch on a GPU machine that has no Rust and no data of its
# own (README.md beside this file, "Training on an accelerator"). It expects, in the folder
# named by PACK (default .dev, relative to the repository root):
#   ds.xz           an x86-64 `drivescript` built here (`strip`, then `xz -9`)
#   scenes.tar.xz   the corpora, one folder each: commonroad-ngsim, commonroad-sumo,
#                   commonroad-scenario-factory (and any more listed in URBAN)
# and trains two networks side by side (A: the checkpoint's width; B: --d ${WIDE:-128}) for
# M minutes each, writing A.tar and B.tar (each best/ and last/ checkpoint) and the logs to OUT.
# env: OUT, M (minutes), REV (git revision to record), LIMIT (seconds the whole call may run),
#      BATCH (256), FROM (data/cities-wip), URBAN (extra --urban folders inside the pack).
set -u
cd "$(dirname "$0")/../.."
T0=$(date +%s)
PY=${PY:-python3}
PACK=${PACK:-.dev}
LIMIT=${LIMIT:-560}
FROM=${FROM:-data/cities-wip}
log() { echo "[$(( $(date +%s) - T0 )) s] $*"; }
export PYTHONUNBUFFERED=1
nvidia-smi -L 2>&1 | head -2
$PY benches/torch/unpack.py "$PACK" scenes.tar.xz /tmp/scn || exit 1
log extracted
rm -rf /tmp/exp /tmp/A /tmp/B
extra=""
for u in ${URBAN:-}; do extra="$extra /tmp/scn/$u"; done
/tmp/ds train --export /tmp/exp --resume "$FROM" --data /tmp/scn/commonroad-ngsim \
  --urban /tmp/scn/commonroad-sumo /tmp/scn/commonroad-scenario-factory $extra 2>&1 \
  | grep -v "scenes read\|files written"
log exported
LEFT=$(( LIMIT - ($(date +%s) - T0) - 15 ))
log "trainings may run $LEFT s"
timeout $LEFT $PY benches/torch/train.py /tmp/exp /tmp/A --check "$FROM" --minutes $M \
  --batch ${BATCH:-256} --revision $REV > $OUT/a.log 2>&1 &
PA=$!
timeout $LEFT $PY benches/torch/train.py /tmp/exp /tmp/B --d ${WIDE:-128} --minutes $M \
  --batch ${BATCH:-256} --revision $REV > $OUT/b.log 2>&1 &
PB=$!
sleep 90
nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv 2>&1
wait $PA; echo "A exit $?"; wait $PB; echo "B exit $?"
log trained
tar cf $OUT/A.tar -C /tmp A; tar cf $OUT/B.tar -C /tmp B
log done
