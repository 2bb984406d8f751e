#!/usr/bin/env bash
# Cuts the held-out evaluation instances from the NGSIM validation scenes (the scenes whose id
# hashes to 0 mod 10, see train::is_validation): one instance every 2 s of each recording,
# from 1 s in (11 history steps) while at least one future step remains.
# Usage: data/checkpoint/heldout.sh NGSIM_DIR OUT_DIR [DRIVESCRIPT]
set -euo pipefail
src=${1:?NGSIM directory (../shared/data/commonroad-ngsim)}
out=${2:?output directory}
bin=${3:-target/release/drivescript}
mkdir -p "$out"
for id in USA_Lanker-1_15_T-1 USA_Lanker-1_2_T-1 USA_Lanker-1_8_T-1 USA_Lanker-2_14_T-1 \
          USA_Lanker-2_21_T-1 USA_US101-13_4_T-1 USA_US101-1_1_T-1 USA_US101-27_1_T-1; do
  steps=$("$bin" inspect "$src/$id.xml.gz" | awk '/^time/ {print $2}')
  for ((c = 10; c + 1 < steps; c += 20)); do
    "$bin" convert "$src/$id.xml.gz" -o "$out/${id}_c$c.yaml" --current-step "$c" --id "${id}_c$c" >/dev/null
  done
done
ls "$out" | wc -l
