#!/usr/bin/env python3
"""How often a moving vehicle's direction of motion turns by more than 0.1 rad between the step
into the current one and the first step of its future: in rollouts (`ROLLOUT_DIR/*_K.json, K < 10`),
or with `--log SCENE_DIR` in the recorded scenes (`SCENE_DIR/ID.yaml`, needs PyYAML) of the
same rollouts. Vehicles at 2 m/s or more at the current step count.

Usage: first_step_turns.py ROLLOUT_DIR [--log SCENE_DIR]
"""
import glob
import json
import math
import os
import sys


def wrap(a):
    return (a + math.pi) % (2 * math.pi) - math.pi


def turns(states, c, dt):
    """None if the vehicle is not observed around c or slower than 2 m/s, else the turn."""
    if len(states) < c + 2 or not all(s and (len(s) < 4 or s[3]) for s in states[c - 1:c + 2]):
        return None
    if math.dist(states[c][:2], states[c - 1][:2]) / dt < 2.0:
        return None
    d = lambda a, b: math.atan2(b[1] - a[1], b[0] - a[0])
    return abs(wrap(d(states[c], states[c + 1]) - d(states[c - 1], states[c])))


roll = sys.argv[1]
log = sys.argv[3] if len(sys.argv) > 3 and sys.argv[2] == "--log" else None
n = big = 0
worst = (0.0, None)
for f in sorted(glob.glob(os.path.join(roll, "*_[0-9].json"))):
    r = json.load(open(f))
    c, dt = r["current_step"], r["dt"]
    if log:
        import yaml
        if not f.endswith("_0.json"):
            continue
        sid = os.path.basename(f)[: -len("_0.json")]
        loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
        scene = yaml.load(open(os.path.join(log, sid + ".yaml")), Loader=loader)
        agents = [(a["id"], a["states"]) for a in scene["agents"] if a.get("type", "vehicle") == "vehicle"]
    else:
        agents = [(a["id"], a["states"]) for a in r["agents"] if a.get("type", "vehicle") == "vehicle"]
    for aid, states in agents:
        t = turns(states, c, dt)
        if t is None:
            continue
        n += 1
        big += t > 0.1
        if t > worst[0]:
            worst = (t, (os.path.basename(f), aid))
print(f"{'log of ' if log else ''}{roll}: {n} moving vehicles; direction of motion turns by more "
      f"than 0.1 rad in the first step: {big}; largest {worst[0]:.2f} rad {worst[1]}")
