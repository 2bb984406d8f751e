#!/usr/bin/env bash
# Cuts held-out evaluation instances from the urban corpora (simulated SUMO traffic on
# OpenStreetMap maps: say so beside every figure), a town at a time: the towns of validation
# fold FOLD (see `inspect`'s `town fold` line and `train --urban`) and the towns named in
# TOWNS, which the cities checkpoint held out. Same layout as heldout.sh:
#   OUT/val        one instance every 2 s of each recording from 1 s in (11 history steps)
#                  while a future step remains: conditional and unconditional evaluation.
#   OUT/behaviour  one instance every 1 s: behaviour success rates.
#   OUT/windows    one instance every 4 s: futures that do not overlap at 4 s.
# Usage: FOLD=0 TOWNS="DEU_Reutlingen" data/checkpoint/heldout_cities.sh OUT_DIR DIR... 
set -euo pipefail
out=${1:?output directory}
shift
fold=${FOLD:-0}
towns=${TOWNS:-DEU_Reutlingen}
bin=${BIN:-target/release/drivescript}
mkdir -p "$out/val" "$out/behaviour" "$out/windows"
n=0
for dir in "$@"; do
  for file in "$dir"/*.xml*; do
    info=$("$bin" inspect "$file")
    id=$(awk '/^scene / {print $2}' <<<"$info")
    town=${id%%-*}
    f=$(awk '/^town fold / {print $3}' <<<"$info")
    if [ "$f" != "$fold" ] && ! grep -qw -- "$town" <<<"$towns"; then
      continue
    fi
    steps=$(awk '/^time/ {print $2}' <<<"$info")
    for ((c = 10; c + 1 < steps; c += 10)); do
      "$bin" convert "$file" -o "$out/behaviour/${id}_c$c.yaml" --current-step "$c" --id "${id}_c$c" >/dev/null
      if (((c - 10) % 20 == 0)); then cp "$out/behaviour/${id}_c$c.yaml" "$out/val/"; fi
      if (((c - 10) % 40 == 0)); then cp "$out/behaviour/${id}_c$c.yaml" "$out/windows/"; fi
    done
    n=$((n + 1))
  done
done
echo "fold $fold + $towns: $n scenes; $(ls "$out/val" | wc -l) validation, $(ls "$out/behaviour" | wc -l) behaviour, $(ls "$out/windows" | wc -l) window instances"
