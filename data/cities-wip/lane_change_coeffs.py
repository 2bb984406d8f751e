#!/usr/bin/env python3
"""How far a lane change lies in a checkpoint's coefficient space.

Projects a lane change (a smooth-step offset of OFFSET metres across the current heading or
route, over SECONDS, speed held) onto the checkpoint's PCA basis and prints each coefficient
divided by the normaliser's scale: the units guidance is clamped in. A future told against a
route (route-frame checkpoints) and one told against the current heading (the shipped
checkpoint) have the same form here, `[along, across, heading]` per future step beyond the
constant-speed anchor. Standard library only.

Usage: lane_change_coeffs.py CHECKPOINT_DIR [OFFSET=3.7] [SECONDS=4]
"""
import json
import sys

ck = sys.argv[1]
offset = float(sys.argv[2]) if len(sys.argv) > 2 else 3.7
seconds = float(sys.argv[3]) if len(sys.argv) > 3 else 4.0
meta = json.load(open(f"{ck}/config.json"))
pca, std = meta["normaliser"]["pca"], meta["normaliser"]["std"]
dim, k = pca["dim"], len(pca["variances"])
future = dim // 3
steps = round(seconds * 10)
x = []
for j in range(future):
    t = min((j + 1) / steps, 1.0)
    x += [0.0, offset * (3 * t * t - 2 * t ** 3), 0.0]
centred = [a - m for a, m in zip(x, pca["mean"])]
comps = [pca["components"][i * dim:(i + 1) * dim] for i in range(k)]
z = [sum(c * v for c, v in zip(row, centred)) for row in comps]
recon = [m + sum(z[i] * comps[i][d] for i in range(k)) for d, m in enumerate(pca["mean"])]
err = max(abs(recon[3 * j + 1] - x[3 * j + 1]) for j in range(future))
scaled = [abs(a / s) for a, s in zip(z, std)]
print(f"{ck}: {k} components; a {offset} m lane change over {seconds} s: largest "
      f"|coefficient / scale| {max(scaled):.1f} (component {scaled.index(max(scaled))}), "
      f"reconstructed to {err:.3f} m across")
