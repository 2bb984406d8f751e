"""Cars that stand (under 0.2 m/s) throughout their recorded future, and what a rollout made of
them over the first 4 s: the sampled path length, the net displacement, how many start to
drive (net over 2 m), how often the motion along the heading changes sign (wobble), and the
path of those that stay; then their sampled speeds per step (count, mean, median, 90th
percentile, m/s).

    python3 standing_wobble.py SCENES_DIR ROLLOUTS_DIR      (needs PyYAML)

SCENES_DIR holds the YAML scenes the rollouts were sampled from; ROLLOUTS_DIR what `simulate
-o` wrote (SCENE_0.json, the first sample).
"""
import glob
import json
import math
import os
import sys

import yaml


def main():
    log_dir, roll_dir = sys.argv[1], sys.argv[2]
    rows, speeds = [], []
    for f in sorted(glob.glob(os.path.join(log_dir, "*.yaml"))):
        stem = os.path.basename(f)[:-5]
        r = os.path.join(roll_dir, stem + "_0.json")
        if not os.path.exists(r):
            continue
        log = yaml.load(open(f), Loader=yaml.CSafeLoader)
        c = log["current_step"]
        rollout = {a["id"]: a for a in json.load(open(r))["agents"]}
        for a in log["agents"]:
            if a.get("type", "vehicle") != "vehicle" or a.get("static"):
                continue
            fut = a["states"][c:c + 41]
            if len(fut) < 11 or any(s is None or len(s) < 2 for s in fut):
                continue
            v = [math.hypot(fut[i + 1][0] - fut[i][0], fut[i + 1][1] - fut[i][1]) / 0.1
                 for i in range(len(fut) - 1)]
            if max(v) >= 0.2 or a["id"] not in rollout:
                continue
            window = rollout[a["id"]]["states"][c:c + 41]
            speeds += [math.hypot(q[0] - p[0], q[1] - p[1]) / 0.1
                       for p, q in zip(window, window[1:]) if p[3] and q[3]]
            rs = [s for s in window if s[3]]
            path = sum(math.hypot(rs[i + 1][0] - rs[i][0], rs[i + 1][1] - rs[i][1])
                       for i in range(len(rs) - 1))
            net = math.hypot(rs[-1][0] - rs[0][0], rs[-1][1] - rs[0][1])
            cs, sn = math.cos(rs[0][2]), math.sin(rs[0][2])
            along = [(rs[i + 1][0] - rs[i][0]) * cs + (rs[i + 1][1] - rs[i][1]) * sn
                     for i in range(len(rs) - 1)]
            # Sign changes of steps longer than 5 mm: back and forth, not rounding.
            flips = sum(1 for i in range(len(along) - 1)
                        if along[i] * along[i + 1] < 0 and abs(along[i]) > 0.005
                        and abs(along[i + 1]) > 0.005)
            rows.append((path, net, flips))
    n = len(rows)
    if n == 0:
        sys.exit("no standing car with a rollout")
    drive = sum(1 for _, net, _ in rows if net > 2.0)
    stay = [p for p, net, _ in rows if net <= 2.0]
    print(f"{n} standing cars: mean path {sum(r[0] for r in rows) / n:.2f} m, "
          f"mean net {sum(r[1] for r in rows) / n:.2f} m, start to drive (net > 2 m) {drive}, "
          f"mean sign changes {sum(r[2] for r in rows) / n:.1f}, "
          f"path of those that stay (net <= 2 m) {sum(stay) / max(1, len(stay)):.2f} m")
    speeds.sort()
    m = len(speeds)
    print(f"sampled speeds: n {m} mean {sum(speeds) / m:.2f} median {speeds[m // 2]:.2f} "
          f"p90 {speeds[int(0.9 * m)]:.2f}")


if __name__ == "__main__":
    main()
