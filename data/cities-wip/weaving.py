"""How much vehicles turn while they drive: the angular speed |heading change| / dt between
consecutive future steps, by speed band (m/s over that step): steps counted, the share under
0.02 rad/s, and the median. Then how often the sign of the turn flips between consecutive
steps where it is over 0.02 rad/s and the car moves faster than 3 m/s: step-to-step jitter
flips often, slow weaving (S-curves over seconds) seldom.

    python3 weaving.py [--horizon STEPS] ROLLOUT_DIR...

Each ROLLOUT_DIR holds what `simulate -o` wrote (SCENE_0.json, the first sample), or the log
as rollouts (`drivescript convert SCENE.yaml -o DIR/SCENE_0.json` for each scene). Only
vehicles count; steps where either end is not observed are skipped, and so are steps past
--horizon (the log runs on past what `simulate --horizon` sampled). Only the Python standard
library.
"""
import argparse
import glob
import json
import math
import os
import sys

BANDS = [(0, 1), (1, 3), (3, 8), (8, math.inf)]


def turns(path, horizon):
    """(angular speed, speed) of each observed step of each vehicle in one rollout file."""
    r = json.load(open(path))
    dt, c = r["dt"], r["current_step"]
    for a in r["agents"]:
        if a["type"] != "vehicle":
            continue
        st = a["states"]
        out = []
        for k in range(c, min(len(st) - 1, c + horizon)):
            p, q = st[k], st[k + 1]
            if p[3] and q[3]:
                w = ((q[2] - p[2] + math.pi) % (2 * math.pi) - math.pi) / dt
                out.append((w, math.hypot(q[0] - p[0], q[1] - p[1]) / dt))
        yield out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--horizon", type=int, default=10**9, help="future steps counted")
    ap.add_argument("dirs", nargs="+")
    a = ap.parse_args()
    for d in a.dirs:
        files = sorted(glob.glob(os.path.join(d, "*_0.json")))
        if not files:
            sys.exit(f"weaving.py: {d}: no *_0.json rollouts")
        bands = {b: [] for b in BANDS}
        flips = pairs = 0
        for f in files:
            for steps in turns(f, a.horizon):
                for w, v in steps:
                    for lo, hi in BANDS:
                        if lo <= v < hi:
                            bands[(lo, hi)].append(abs(w))
                signs = [w > 0 for w, v in steps if v > 3 and abs(w) > 0.02]
                pairs += max(len(signs) - 1, 0)
                flips += sum(a != b for a, b in zip(signs, signs[1:]))
        print(f"{d} ({len(files)} rollouts)")
        for (lo, hi), ws in bands.items():
            if not ws:
                continue
            ws.sort()
            under = sum(w < 0.02 for w in ws) / len(ws)
            print(
                f"  {lo:g}-{hi:g} m/s: {len(ws)} steps, {under:.2f} under 0.02 rad/s, "
                f"median {ws[len(ws) // 2]:.3f} rad/s"
            )
        print(f"  sign flips: {flips / max(pairs, 1):.3f} of {pairs} step pairs")


if __name__ == "__main__":
    main()
