#!/usr/bin/env python3
"""Writes a YAML scene of N cars on an 8-lane straight road (2 km), 91 steps: the crowd the
scaling figures of docs/model.md were measured on.

    python3 benches/crowd/make.py 2000 > /tmp/crowd.yaml
"""
import sys

n = int(sys.argv[1]) if len(sys.argv) > 1 else 2000
lanes, length = 8, 2000
per_lane = -(-n // lanes)
print("scenario_id: crowd\ndt: 0.1\nsteps: 91\ncurrent_step: 10")
print(f"road: {{lanes: {lanes}, length: {length}}}\nagents:")
k = 0
for lane in range(lanes):
    for j in range(per_lane):
        if k == n:
            break
        # 8 m apart, 10 m/s: a dense queue that stays on the road for the 9 s.
        print(f"  - {{id: {k}, lane: {lane}, s: {8 * j + 1}, speed: 10}}")
        k += 1
