#!/usr/bin/env bash
# Cuts the held-out evaluation instances used in data/checkpoint/README.md.
#   OUT/val        the 8 NGSIM validation scenes (the scenes whose id hashes to 0 mod 10, see
#                  train::is_validation), one instance every 2 s of each recording from 1 s in
#                  (11 history steps) while a future step remains: conditional and
#                  unconditional evaluation.
#   OUT/behaviour  the same scenes plus the two NGSIM CommonRoad samples that are not in the
#                  training corpus (data/samples/commonroad/USA_Peach-4_8_T-1.xml,
#                  USA_US101-3_3_T-1.xml), one instance every 1 s: behaviour success rates.
# Usage: data/checkpoint/heldout.sh NGSIM_DIR OUT_DIR [DRIVESCRIPT]
set -euo pipefail
src=${1:?NGSIM directory (../shared/data/commonroad-ngsim)}
out=${2:?output directory}
bin=${3:-target/release/drivescript}
here=$(cd "$(dirname "$0")/../.." && pwd)
cut() { # file id every dir
  local steps
  steps=$("$bin" inspect "$1" | awk '/^time/ {print $2}')
  for ((c = 10; c + 1 < steps; c += $3)); do
    "$bin" convert "$1" -o "$4/${2}_c$c.yaml" --current-step "$c" --id "${2}_c$c" >/dev/null
  done
}
mkdir -p "$out/val" "$out/behaviour"
for id in USA_Lanker-1_15_T-1 USA_Lanker-1_2_T-1 USA_Lanker-1_8_T-1 USA_Lanker-2_14_T-1 \
          USA_Lanker-2_21_T-1 USA_US101-13_4_T-1 USA_US101-1_1_T-1 USA_US101-27_1_T-1; do
  cut "$src/$id.xml.gz" "$id" 20 "$out/val"
  cut "$src/$id.xml.gz" "$id" 10 "$out/behaviour"
done
for id in USA_Peach-4_8_T-1 USA_US101-3_3_T-1; do
  cut "$here/data/samples/commonroad/$id.xml" "$id" 10 "$out/behaviour"
done
echo "$(ls "$out/val" | wc -l) validation instances, $(ls "$out/behaviour" | wc -l) behaviour instances"
