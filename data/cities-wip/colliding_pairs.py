#!/usr/bin/env python3
"""Counts the pairs of road users whose boxes overlap in a run's rollouts, by kind.

Usage: colliding_pairs.py ROLLOUT_DIR [--list]

Reads sample 0 of each rollout (NAME_0.json, as `simulate -o` or `convert -o x.json` write
them) and, over the future steps, finds each pair of valid agents whose oriented boxes
overlap (separating axes). A pair counts once per rollout, at its first overlapping step,
and is classed by the difference of the two headings there: head-on above 2 rad, same way
below 0.5 rad, crossing between. Agents are vehicles, "small" vehicles (shorter than 2.5 m:
mopeds and motorcycles), cyclists or pedestrians. `eval`'s collision rate counts vehicles
that collide; this says which pairs and how, for finding what to fix.

Only the Python standard library.
"""
import collections
import glob
import json
import math
import os
import sys


def corners(x, y, h, length, width):
    c, s = math.cos(h), math.sin(h)
    return [
        (x + c * dx - s * dy, y + s * dx + c * dy)
        for dx, dy in ((length / 2, width / 2), (length / 2, -width / 2),
                       (-length / 2, -width / 2), (-length / 2, width / 2))
    ]


def overlap(a, b):
    for poly in (a, b):
        for i in range(4):
            p, q = poly[i], poly[(i + 1) % 4]
            nx, ny = q[1] - p[1], p[0] - q[0]
            pa = [nx * x + ny * y for x, y in a]
            pb = [nx * x + ny * y for x, y in b]
            if max(pa) <= min(pb) or max(pb) <= min(pa):
                return False
    return True


def kind_of(agent):
    if agent["type"] == "vehicle" and agent["length"] < 2.5:
        return "small"
    return agent["type"]


def pairs(path):
    d = json.load(open(path))
    c, agents = d["current_step"], d["agents"]
    seen, out = set(), []
    steps = max(len(a["states"]) for a in agents)
    for t in range(c + 1, steps):
        live = [(i, a, a["states"][t]) for i, a in enumerate(agents)
                if t < len(a["states"]) and a["states"][t][3]]
        for u in range(len(live)):
            i, a, s = live[u]
            for j, b, r in live[u + 1:]:
                # Boxes of road users are under 15 m long: farther centres cannot touch.
                if (i, j) in seen or abs(s[0] - r[0]) + abs(s[1] - r[1]) > 15:
                    continue
                if overlap(corners(s[0], s[1], s[2], a["length"], a["width"]),
                           corners(r[0], r[1], r[2], b["length"], b["width"])):
                    seen.add((i, j))
                    dh = abs(math.remainder(s[2] - r[2], math.tau))
                    how = "head-on" if dh > 2 else "same way" if dh < 0.5 else "crossing"
                    who = " / ".join(sorted((kind_of(a), kind_of(b))))
                    out.append((d["scene_id"], t - c, a["id"], b["id"], who, how, dh))
    return out


def main():
    if len(sys.argv) < 2 or sys.argv[1].startswith("-"):
        sys.exit(__doc__)
    files = sorted(glob.glob(os.path.join(sys.argv[1], "*_0.json")))
    if not files:
        sys.exit(f"{sys.argv[1]}: no rollout (NAME_0.json) there")
    rows = [p for f in files for p in pairs(f)]
    if "--list" in sys.argv[2:]:
        for r in rows:
            print(f"{r[0]} t+{r[1]} {r[2]}-{r[3]} {r[4]} {r[5]} ({r[6]:.2f} rad)")
    how = collections.Counter(r[5] for r in rows)
    print(f"{len(files)} rollouts, {len(rows)} colliding pairs: "
          + ", ".join(f"{k} {how[k]}" for k in ("head-on", "same way", "crossing")))
    for (who, k), n in sorted(collections.Counter((r[4], r[5]) for r in rows).items()):
        print(f"  {n:4d} {who}, {k}")


if __name__ == "__main__":
    main()
