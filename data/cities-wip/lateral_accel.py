"""Per vehicle of a directory of YAML scenes (`drivescript convert` writes them), the largest
lateral acceleration v·ω over its recorded future, with velocities from centred differences
over 0.6 s, 1 s and 2 s windows (the judge's is 0.6 s), counted where the car is faster than
3 m/s. Prints the fraction of vehicles above 5, 6 and 7 m/s² per window, and the worst
(lateral acceleration, speed, yaw rate) of the first cars flagged at 0.6 s.

    python3 lateral_accel.py SCENES_DIR [--horizon STEPS]      (needs PyYAML)
"""
import argparse
import glob
import math
import os

import yaml

DT = 0.1


def velocity(st, t, h):
    p, q = st[t - h], st[t + h]
    return ((q[0] - p[0]) / (2 * h * DT), (q[1] - p[1]) / (2 * h * DT))


def worst_lateral(st, c, horizon, h):
    """(lateral acceleration, speed, yaw rate) where |v·ω| is largest, or zeros."""
    best = (0.0, None, None)
    for t in range(c + 1, min(len(st), c + horizon + 1)):
        lo, hi = t - 2 * h, t + 2 * h
        if lo < 0 or hi >= len(st) or any(s is None for s in st[lo:hi + 1]):
            continue
        va, vb = velocity(st, t - h, h), velocity(st, t + h, h)
        if math.hypot(*va) < 3 or math.hypot(*vb) < 3:
            continue
        turn = math.atan2(vb[1], vb[0]) - math.atan2(va[1], va[0])
        omega = ((turn + math.pi) % (2 * math.pi) - math.pi) / (2 * h * DT)
        v = math.hypot(*velocity(st, t, h))
        if abs(v * omega) > best[0]:
            best = (abs(v * omega), v, omega)
    return best


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes")
    ap.add_argument("--horizon", type=int, default=40, help="future steps judged")
    a = ap.parse_args()
    rows = []
    for f in sorted(glob.glob(os.path.join(a.scenes, "*.yaml"))):
        scene = yaml.load(open(f), Loader=yaml.CSafeLoader)
        c = scene["current_step"]
        for ag in scene["agents"]:
            if ag.get("type", "vehicle") != "vehicle" or ag.get("static"):
                continue
            st = [s if s is not None and len(s) >= 2 else None for s in ag["states"]]
            rows.append([worst_lateral(st, c, a.horizon, h) for h in (3, 5, 10)])
    n = len(rows)
    print(n, "vehicles")
    for i, name in enumerate(["0.6 s", "1.0 s", "2.0 s"]):
        v = [r[i][0] for r in rows]
        print(f"{name} windows: " + "  ".join(f">{b} {sum(x > b for x in v) / n:.3f}" for b in (5, 6, 7)))
    flagged = [r for r in rows if r[0][0] > 5]
    print(len(flagged), "flagged at 0.6 s; (lateral m/s², speed m/s, yaw rate rad/s) at 0.6 / 1.0 / 2.0 s:")
    for r in flagged[:15]:
        print([tuple(round(x, 2) for x in q) if q[1] else None for q in r])


if __name__ == "__main__":
    main()
