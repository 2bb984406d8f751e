"""What the Python layer adds to a cost evaluation over `drivescript bench cost`, and how
evaluate_batch scales.

The scene and trajectories are the bench's: `Scene.load(path).crop(24, 80)` and its
`filled_future()`, with the bench's parameters (victim = the first agent, cutter = the second).
Each round runs `drivescript bench cost --scene PATH --seconds S` (the Rust figure: a tight
loop of `CostScript::evaluate`), then times `script.evaluate(scene, traj)` from Python the same
way (a loop of calls for at least S seconds, mean per call), script by script; the table
gives medians over the rounds. Then a batch of 64 through `evaluate_batch` against 64 single calls. Run from
the repository root after `cargo build --release`, with the package importable:

    python benches/python/overhead.py [--rounds 5] [--seconds 1]
"""

import argparse
import os

# numpy's BLAS threads are kept off the cores being timed (set before numpy is imported).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pathlib  # noqa: E402
import re  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

import drivescript as ds  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[2]
SHARED = ROOT / "../shared/data/commonroad-ngsim/USA_US101-23_1_T-1.xml.gz"
SAMPLE = ROOT / "data/samples/commonroad/USA_US101-4_1_T-1.xml"
NAMES = ["cut_in", "rightmost_lane", "no_collisions"]


def rust_row_us(cli, scene_path, seconds):
    """Script µs per call of each of NAMES, from one `drivescript bench cost` run."""
    out = subprocess.run(
        [cli, "bench", "cost", "--scene", str(scene_path), "--seconds", str(seconds)],
        capture_output=True, text=True, check=True,
    ).stdout
    rows = {}
    for line in out.splitlines():
        m = re.match(r"\|\s*([a-z_]+)\s*\|\s*([0-9.]+)\s*\|", line)
        if m and m.group(1) in NAMES:
            rows[m.group(1)] = float(m.group(2))
    missing = [n for n in NAMES if n not in rows]
    if missing:
        raise SystemExit(f"`drivescript bench cost` printed no row for {missing}:\n{out}")
    return rows


def python_us(script, scene, traj, seconds):
    """Mean µs per `script.evaluate(scene, traj)` in a loop of at least `seconds` (as
    `bench cost` times a call: nothing else in the loop), and the engine's own median time per
    call (CostResult.eval_ms) from a second, shorter loop."""
    script.evaluate(scene, traj)
    reps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds or reps < 3:
        for _ in range(10):
            script.evaluate(scene, traj)
        reps += 10
    wall = (time.perf_counter() - start) / reps * 1e6
    engine = [script.evaluate(scene, traj).eval_ms * 1e3 for _ in range(min(reps, 200))]
    return wall, statistics.median(engine)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=1.0, help="per row and round, as bench cost's")
    ap.add_argument("--scene", type=pathlib.Path, default=SHARED if SHARED.exists() else SAMPLE)
    ap.add_argument("--cli", default=os.environ.get("DRIVESCRIPT_BIN") or str(ROOT / "target/release/drivescript"))
    args = ap.parse_args()
    scene = ds.Scene.load(args.scene).crop(24, 80)
    traj = scene.filled_future()
    v, c = scene.agent_ids[0], scene.agent_ids[1]
    scripts = {
        "cut_in": ds.CostScript.from_file(ROOT / "scripts/cut_in.rhai", params={"cutter": c, "victim": v}),
        "rightmost_lane": ds.CostScript.from_file(ROOT / "scripts/rightmost_lane.rhai", params={"vehicle": v}),
        "no_collisions": ds.CostScript.from_file(ROOT / "scripts/no_collisions.rhai", params={"margin": 0.5}),
    }
    print(f"scene {scene.scenario_id} ({args.scene}): {len(scene.agent_ids)} agents x {traj.shape[1]} "
          f"steps, victim {v}, cutter {c}; {os.cpu_count()} cores; {args.rounds} interleaved rounds of "
          f"{args.seconds} s per row")
    rust = {n: [] for n in NAMES}
    py = {n: [] for n in NAMES}
    engine = {n: [] for n in NAMES}
    for _ in range(args.rounds):
        for n, us in rust_row_us(args.cli, args.scene, args.seconds).items():
            rust[n].append(us)
        for n, s in scripts.items():
            wall, eng = python_us(s, scene, traj, args.seconds)
            py[n].append(wall)
            engine[n].append(eng)
    print("| cost | Rust bench µs | Python evaluate µs | Python adds | engine µs (eval_ms) | batch 64 ms | 64 single ms | batch speed-up |")
    print("|---|---|---|---|---|---|---|---|")
    batch = np.stack([traj] * 64)
    for n, s in scripts.items():
        r, p, e = (statistics.median(x[n]) for x in (rust, py, engine))
        s.evaluate_batch(scene, batch)
        bm, sm = [], []
        for _ in range(5):
            t = time.perf_counter()
            s.evaluate_batch(scene, batch)
            bm.append((time.perf_counter() - t) * 1e3)
            t = time.perf_counter()
            for b in batch:
                s.evaluate(scene, b)
            sm.append((time.perf_counter() - t) * 1e3)
        b, sg = statistics.median(bm), statistics.median(sm)
        print(f"| {n} | {r:.1f} | {p:.1f} | {100 * (p - r) / r:+.1f} % | {e:.1f} | {b:.1f} | {sg:.1f} | {sg / b:.2f}x |")


if __name__ == "__main__":
    main()
