#!/usr/bin/env bash
# Behaviour success on held-out instances, every behaviour in one run, with the figures the
# plausibility issue asks for side by side: for each behaviour, the instances checked, the
# rate achieved plausibly (the headline), the rate achieved (geometry alone), the baselines'
# rates achieved plausibly (log replay / constant velocity / lane following), the fractions of
# all vehicles that collide and that a car could not drive in the guided samples, and the same
# fractions in the log and in unguided samples of the same instances (same seed). Each guided
# sample is judged against its unguided twin (`eval --unguided`): it passes only when the
# vehicles the behaviour does not name fare no worse, within the tolerance in docs/evaluation.md.
#   INSTANCES  a directory cut by heldout.sh (OUT/behaviour or OUT/windows)
#   OUT        where rollouts and eval JSON go (one directory per behaviour, plus unguided/)
#   extra arguments go to every `simulate` (e.g. --guidance denoiser, --lambda 2)
#   BEHAVIOURS="cut_in yield" in the environment measures only those (default: all fourteen)
# Usage: data/checkpoint/behaviours.sh INSTANCES OUT [CHECKPOINT [DRIVESCRIPT]] [-- SIMULATE_ARGS...]
set -euo pipefail
inst=${1:?instances directory (heldout.sh OUT/behaviour)}
out=${2:?output directory}
shift 2
ckpt=data/checkpoint
bin=target/release/drivescript
if [ $# -gt 0 ] && [ "$1" != "--" ]; then ckpt=$1; shift; fi
if [ $# -gt 0 ] && [ "$1" != "--" ]; then bin=$1; shift; fi
if [ $# -gt 0 ] && [ "$1" = "--" ]; then shift; fi
extra=("$@")
horizon=$(grep -o '"future": *[0-9]*' "$ckpt/config.json" | head -1 | grep -o '[0-9]*$')
# Each behaviour's rollouts go to a fresh OUT/NAME: a directory from an earlier run would be
# refused by simulate and its old rollouts scored by eval.
if [ -e "$out" ] && [ -n "$(ls -A "$out")" ]; then
    echo "$out is not empty: give a new OUT" >&2
    exit 1
fi
mkdir -p "$out"
# The model's own rate: unguided samples of the same instances.
"$bin" simulate "$inst" --checkpoint "$ckpt" --task unconditional -o "$out/unguided" \
    "${extra[@]}" >"$out/unguided.log"
unguided=$("$bin" eval "$inst" --task unconditional --rollouts "$out/unguided" \
    --horizon "$horizon" | awk -F'|' '/^\| rollouts/ {gsub(/ /, "", $7); gsub(/ /, "", $8); print $7 " / " $8}')
printf '| behaviour | instances | achieved plausibly | achieved | baselines: log / cv / lane | collided vehicles (log) | implausible vehicles (log) | unguided: collided / implausible |\n'
printf '|---|---|---|---|---|---|---|---|\n'
all="cut_in rightmost_lane off_road yield speed_limit target_point no_collisions
    lane_change_left lane_change_right follow reverse weave stop accident"
for b in ${BEHAVIOURS:-$all}; do
    # A scene that fails is reported and the rest go on, as in simulate itself.
    "$bin" simulate "$inst" --checkpoint "$ckpt" --task unconditional --auto "$b" \
        -o "$out/$b" "${extra[@]}" >"$out/$b.log" 2>&1 ||
        echo "$b: simulate reported failures, see $out/$b.log" >&2
    "$bin" eval "$inst" --task behaviour --behaviour "$b" --auto --baseline log --baseline cv --baseline lane \
        --rollouts "$out/$b" --unguided "$out/unguided" --horizon "$horizon" --json "$out/$b.json" >"$out/$b.eval" 2>"$out/$b.eval.err" ||
        echo "$b: eval reported errors, see $out/$b.eval.err" >&2
    # No instance of a behaviour (no agents suited to it in any scene) is a row saying so.
    if ! grep -q '^| rollouts' "$out/$b.eval"; then
        printf '| %s | 0 | - | - | - | - | - | %s |\n' "$b" "$unguided"
        continue
    fi
    awk -F'|' -v b="$b" -v u="$unguided" '
        /^\| log replay/ {for (i = 5; i <= 8; i++) gsub(/ /, "", $i); log_p = $5; log_c = $7; log_rate = $8}
        /^\| constant velocity/ {gsub(/ /, "", $5); cv_p = $5}
        /^\| constant speed along lane/ {gsub(/ /, "", $5); lane_p = $5}
        /^\| rollouts/ {for (i = 4; i <= 8; i++) gsub(/ /, "", $i); n = $4; p = $5; a = $6; c = $7; m = $8}
        END {printf "| %s | %s | %s | %s | %s / %s / %s | %s (%s) | %s (%s) | %s |\n", b, n, p, a, log_p, cv_p, lane_p, c, log_c, m, log_rate, u}
    ' "$out/$b.eval"
done
