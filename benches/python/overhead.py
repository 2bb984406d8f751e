"""What the Python layer adds to a cost evaluation, and how evaluate_batch scales.

For cut_in, rightmost_lane and no_collisions on the US-101 sample over 80 future steps (its 22
agents, the size `drivescript bench cost` uses when ../shared/data is absent), prints per call:
the wall time of `script.evaluate(scene, traj)` seen from Python, the engine's own time for
the same call (`CostResult.eval_ms`, measured inside Rust around the script's run), and the
difference as a share of the engine's time; then a batch of 64 through `evaluate_batch`
against 64 single calls. Medians of interleaved rounds. Run from the repository root:

    python benches/python/overhead.py [--rounds 15]
"""

import argparse
import os
import pathlib
import statistics
import time

import numpy as np

import drivescript as ds

ROOT = pathlib.Path(__file__).resolve().parents[2]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--calls", type=int, default=20, help="calls per round")
    args = ap.parse_args()
    scene = ds.Scene.load(ROOT / "data/samples/commonroad/USA_US101-4_1_T-1.xml")
    traj = scene.log_future(80)
    scripts = {
        "cut_in": ds.CostScript.from_file(ROOT / "scripts/cut_in.rhai", params={"cutter": 401, "victim": 405}),
        "rightmost_lane": ds.CostScript.from_file(ROOT / "scripts/rightmost_lane.rhai", params={"vehicle": 405}),
        "no_collisions": ds.CostScript.from_file(ROOT / "scripts/no_collisions.rhai", params={"margin": 0.5}),
    }
    print(f"scene {scene.scenario_id}: {len(scene.agent_ids)} agents x {traj.shape[1]} steps; "
          f"{os.cpu_count()} cores; {args.rounds} rounds of {args.calls} calls")
    print("| cost | Python wall us | engine us | Python adds | batch 64 ms | 64 single ms | batch speed-up |")
    print("|---|---|---|---|---|---|---|")
    for name, s in scripts.items():
        s.evaluate(scene, traj)  # compile and validate once, as any first call does
        walls, engines, batches, singles = [], [], [], []
        batch = np.stack([traj] * 64)
        for _ in range(args.rounds):
            for _ in range(args.calls):
                t = time.perf_counter()
                r = s.evaluate(scene, traj)
                walls.append((time.perf_counter() - t) * 1e6)
                engines.append(r.eval_ms * 1e3)
            t = time.perf_counter()
            s.evaluate_batch(scene, batch)
            batches.append((time.perf_counter() - t) * 1e3)
            t = time.perf_counter()
            for b in batch:
                s.evaluate(scene, b)
            singles.append((time.perf_counter() - t) * 1e3)
        w, e = statistics.median(walls), statistics.median(engines)
        bm, sm = statistics.median(batches), statistics.median(singles)
        print(f"| {name} | {w:.1f} | {e:.1f} | {100 * (w - e) / e:.1f} % | {bm:.1f} | {sm:.1f} | {sm / bm:.2f}x |")


if __name__ == "__main__":
    main()
