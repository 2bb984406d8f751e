#!/usr/bin/env bash
# Cuts the held-out evaluation instances used in data/checkpoint/README.md from the NGSIM
# scenes of one validation fold (the scenes whose id hashes to FOLD mod 10, see
# train::is_validation and `inspect`'s `fold` line; the shipped checkpoint holds out fold 0).
#   OUT/val        one instance every 2 s of each recording from 1 s in (11 history steps)
#                  while a future step remains: conditional and unconditional evaluation.
#   OUT/behaviour  one instance every 1 s, and for fold 0 also of the two NGSIM CommonRoad
#                  samples that are not in the training corpus (data/samples/commonroad/
#                  USA_Peach-4_8_T-1.xml, USA_US101-3_3_T-1.xml): behaviour success rates.
#   OUT/windows    one instance every 4 s of the same recordings: their 4 s futures do not
#                  overlap, so each is a separate stretch of traffic (behaviour rates over
#                  independent scenes).
# Usage: data/checkpoint/heldout.sh NGSIM_DIR OUT_DIR [FOLD [DRIVESCRIPT]]
set -euo pipefail
src=${1:?NGSIM directory (../shared/data/commonroad-ngsim)}
out=${2:?output directory}
fold=${3:-0}
bin=${4:-target/release/drivescript}
here=$(cd "$(dirname "$0")/../.." && pwd)
cut() { # file id every dir
  local steps
  steps=$("$bin" inspect "$1" | awk '/^time/ {print $2}')
  for ((c = 10; c + 1 < steps; c += $3)); do
    "$bin" convert "$1" -o "$4/${2}_c$c.yaml" --current-step "$c" --id "${2}_c$c" >/dev/null
  done
}
ids=$("$bin" inspect "$src" | awk -v f="$fold" '/^scene / {id = $2} /^fold / && $2 == f {print id}')
if [ -z "$ids" ]; then
  echo "no scene of $src lies in fold $fold" >&2
  exit 1
fi
mkdir -p "$out/val" "$out/behaviour" "$out/windows"
for id in $ids; do
  file=$(ls "$src/$id".xml* | head -1)
  cut "$file" "$id" 20 "$out/val"
  cut "$file" "$id" 10 "$out/behaviour"
  cut "$file" "$id" 40 "$out/windows"
done
if [ "$fold" = 0 ]; then
  for id in USA_Peach-4_8_T-1 USA_US101-3_3_T-1; do
    cut "$here/data/samples/commonroad/$id.xml" "$id" 10 "$out/behaviour"
    cut "$here/data/samples/commonroad/$id.xml" "$id" 40 "$out/windows"
  done
fi
echo "fold $fold: $(echo $ids | wc -w) scenes; $(ls "$out/val" | wc -l) validation, $(ls "$out/behaviour" | wc -l) behaviour, $(ls "$out/windows" | wc -l) window instances"
