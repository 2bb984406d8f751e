"""Sampled speeds of the cars that stand (< 0.2 m/s) throughout their recorded future.

Usage: python3 standing_speeds.py LOG_DIR ROLLOUT_DIR (scenes as YAML, rollouts of one sample
each, as `simulate` writes them); prints the count, mean, median and 90th percentile (m/s).
"""
import json, sys, glob, os, math
import yaml
log_dir, roll_dir = sys.argv[1], sys.argv[2]
speeds = []
for f in sorted(glob.glob(os.path.join(log_dir, "*.yaml"))):
    stem = os.path.basename(f)[:-5]
    r = os.path.join(roll_dir, stem + "_0.json")
    if not os.path.exists(r):
        continue
    log = yaml.load(open(f), Loader=yaml.CSafeLoader)
    c = log["current_step"]
    ro = {a["id"]: a for a in json.load(open(r))["agents"]}
    for a in log["agents"]:
        if a.get("type", "vehicle") != "vehicle" or a.get("static"):
            continue
        st = a["states"]
        fut = st[c:c + 41]
        if len(fut) < 11 or any(s is None or len(s) < 2 for s in fut):
            continue
        v = [math.hypot(fut[i + 1][0] - fut[i][0], fut[i + 1][1] - fut[i][1]) / 0.1 for i in range(len(fut) - 1)]
        if max(v) >= 0.2 or a["id"] not in ro:
            continue
        rs = ro[a["id"]]["states"][c:c + 41]
        for i in range(len(rs) - 1):
            if rs[i][3] and rs[i + 1][3]:
                speeds.append(math.hypot(rs[i + 1][0] - rs[i][0], rs[i + 1][1] - rs[i][1]) / 0.1)
speeds.sort()
n = len(speeds)
print(f"n {n} mean {sum(speeds)/n:.2f} median {speeds[n//2]:.2f} p90 {speeds[int(0.9*n)]:.2f}")
