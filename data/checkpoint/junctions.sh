#!/usr/bin/env bash
# Writes synthetic yield instances: NGSIM has no pair for which a yield request means something
# (data/checkpoint/README.md, "Requests that mean something"), so these measure the yield
# pipeline (suggest, scripts/yield.rhai, guidance, the checker) where traffic does conflict.
# They are YAML scenes on two maps, each with one pair whose recorded (constant-speed) drive has
# the yielder reach the meeting point first, `lag` seconds before the other:
#   OUT/left_*.yaml   a left turn across oncoming traffic (the map of scripts/scenes/junction.yaml)
#   OUT/merge_*.yaml  an on-ramp joining a main lane (the map of scripts/scenes/merge.yaml)
# The model never saw such maps or cars placed this way (it was trained on NGSIM), so these
# rates say what guidance does out of its training distribution, not what held-out NGSIM gives.
# Usage: data/checkpoint/junctions.sh OUT_DIR
set -euo pipefail
out=${1:?output directory}
mkdir -p "$out"
n=0
# s of the meeting point along each route (metres from the route's first lane's start): the
# left turn crosses the oncoming lane's centre line at (59.3, 3.5); the ramp joins at (150, 0).
scene() { # name, map yaml, yielder route, s_meet_a, v1, t1, other route, s_meet_b, v2, lag
  local s1 s2
  s1=$(awk -v m="$4" -v v="$5" -v t="$6" 'BEGIN {printf "%.2f", m - v * t}')
  s2=$(awk -v m="$8" -v v="$9" -v t="$6" -v l="${10}" 'BEGIN {printf "%.2f", m - v * (t + l)}')
  cat >"$out/$1.yaml" <<EOF
# Synthetic yield instance (data/checkpoint/junctions.sh): vehicle 1 at $5 m/s reaches the
# meeting point in $6 s, vehicle 2 at $9 m/s ${10} s later.
scenario_id: $1
steps: 51
current_step: 10
ego: 1
map:
$2
agents:
  - {id: 1, route: $3, s: $s1, speed: $5}
  - {id: 2, route: $7, s: $s2, speed: $9}
EOF
  n=$((n + 1))
}
left='  lanes:
    - {id: 1, centerline: [[0, 0], [50, 0]], successors: [2, 3]}
    - {id: 2, centerline: [[50, 0], [120, 0]]}
    - {id: 3, centerline: [[50, 0], [56, 1], [60, 4], [62, 10], [62, 60]]}
    - {id: 10, centerline: [[120, 3.5], [50, 3.5]], successors: [11]}
    - {id: 11, centerline: [[50, 3.5], [0, 3.5]]}'
merge='  lanes:
    - {id: 1, centerline: [[0, 0], [150, 0]], successors: [3], type: freeway}
    - {id: 2, centerline: [[0, -30], [100, -8], [150, 0]], successors: [3], type: freeway}
    - {id: 3, centerline: [[150, 0], [320, 0]], type: freeway}
  road_edges:
    - points: [[0, -1.8], [150, -1.8], [320, -1.8]]
    - points: [[320, 1.8], [0, 1.8]]'
for t1 in 1.6 2.2 2.8; do
  for lag in 0.3 0.9; do
    for v1 in 4 6 8; do
      for v2 in 9 13; do
        scene "left_${v1}_${t1}_${v2}_${lag}" "$left" "[1, 3]" 60.25 "$v1" "$t1" "[10, 11]" 60.67 "$v2" "$lag"
      done
    done
    for v1 in 12 16 20; do
      for v2 in 15 22; do
        scene "merge_${v1}_${t1}_${v2}_${lag}" "$merge" "[2, 3]" 153.04 "$v1" "$t1" "[1, 3]" 150 "$v2" "$lag"
      done
    done
  done
done
echo "$n scenes in $out"
