"""Which PCA components carry the wobble of cars that should stand: for each vehicle that stands
(under 0.02 m per step) throughout at least MIN_STEPS recorded future steps, the sampled
future (the checkpoint's full horizon) is projected onto the checkpoint's PCA basis, and the
median distance, per component, from the coefficients of standing still is printed beside
the component's spread over the training futures (metres; headings count as metres, as in
the basis).

    python3 component_error.py SCENES_DIR ROLLOUTS_DIR CHECKPOINT [--min-steps 81]
"""
import argparse
import glob
import json
import math
import os

import yaml


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes")
    ap.add_argument("rollouts")
    ap.add_argument("checkpoint")
    ap.add_argument("--min-steps", type=int, default=81, help="recorded future steps needed")
    a = ap.parse_args()
    meta = json.load(open(os.path.join(a.checkpoint, "config.json")))
    pca = meta["normaliser"]["pca"]
    dim, k = pca["dim"], len(pca["variances"])
    comps = [pca["components"][i * dim:(i + 1) * dim] for i in range(k)]
    mean, future = pca["mean"], dim // 3

    def project(v):
        return [sum((v[i] - mean[i]) * c[i] for i in range(dim)) for c in comps]

    still = project([0.0] * dim)
    errs = [[] for _ in range(k)]
    for f in sorted(glob.glob(os.path.join(a.scenes, "*.yaml"))):
        stem = os.path.basename(f)[:-5]
        r = os.path.join(a.rollouts, stem + "_0.json")
        if not os.path.exists(r):
            continue
        log = yaml.load(open(f), Loader=yaml.CSafeLoader)
        c = log["current_step"]
        rollout = {x["id"]: x for x in json.load(open(r))["agents"]}
        for ag in log["agents"]:
            if ag.get("type", "vehicle") != "vehicle" or ag.get("static") or ag["id"] not in rollout:
                continue
            fut = [s for s in ag["states"][c:] if s is not None and len(s) >= 2]
            if len(fut) < a.min_steps:
                continue
            if max(math.hypot(fut[i + 1][0] - fut[i][0], fut[i + 1][1] - fut[i][1])
                   for i in range(len(fut) - 1)) >= 0.02:
                continue
            rs = rollout[ag["id"]]["states"]
            if len(rs) < c + 1 + future or not all(s[3] for s in rs[c:c + 1 + future]):
                continue
            x0, y0, h0 = rs[c][0], rs[c][1], rs[c][2]
            cs, sn = math.cos(h0), math.sin(h0)
            v, prev = [], 0.0
            for j in range(future):
                s = rs[c + 1 + j]
                dx, dy = s[0] - x0, s[1] - y0
                dh = (s[2] - h0 - prev + math.pi) % (2 * math.pi) - math.pi + prev
                prev = dh
                v += [cs * dx + sn * dy, -sn * dx + cs * dy, dh]
            got = project(v)
            for i in range(k):
                errs[i].append(abs(got[i] - still[i]))
    n = len(errs[0])
    if n == 0:
        raise SystemExit("no standing car with a full-horizon rollout")
    print(n, "standing cars; median |coefficient - standing still| per component, metres "
             "(the component's spread in brackets):")
    print(" ".join(f"{i}:{sorted(e)[len(e) // 2]:.2f}({pca['variances'][i] ** 0.5:.2f})"
                   for i, e in enumerate(errs)))


if __name__ == "__main__":
    main()
