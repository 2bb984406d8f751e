"""Trajectory optimisation in plain PyTorch with a Rhai cost script.

The cutter's recorded positions (US-101, agents 401 and 405) are optimised with Adam against
scripts/cut_in.rhai, whose gradient comes from the Rust engine through ds.torch.cost; the
checker that `drivescript simulate --auto cut_in` uses then judges the result. Run from the
repository root:

    python python/examples/optimise_cut_in.py
"""

import pathlib
import time

import numpy as np
import torch

import drivescript as ds

ROOT = pathlib.Path(__file__).resolve().parents[2]
PARAMS = {"cutter": 401, "victim": 405}


def main() -> None:
    t0 = time.perf_counter()
    scene = ds.Scene.load(ROOT / "data/samples/commonroad/USA_US101-4_1_T-1.xml")
    script = ds.CostScript.from_file(ROOT / "scripts/cut_in.rhai", params=PARAMS)
    log = scene.log_future(40)
    before = script.evaluate(scene, log)
    print(f"recorded: total {before.total:.4f}  " + "  ".join(f"{k} {v:.3f}" for k, v in before.terms.items()))
    print("checker on the recording:", ds.check("cut_in", scene, log, PARAMS))

    # The cutter's positions are the variables (everyone else keeps the log); headings follow
    # the log. A smoothness cost in PyTorch, from the last two recorded states on, composes
    # with the script's cost as tensors do: it keeps the cutter's acceleration plausible.
    a = scene.agent_ids.index(PARAMS["cutter"])
    fixed = torch.tensor(log)
    past = torch.tensor(scene.log_history()[a, -2:, :2])
    xy = torch.tensor(log[a, :, :2], requires_grad=True)
    opt = torch.optim.Adam([xy], lr=0.3)
    for it in range(801):
        opt.zero_grad()
        traj = fixed.clone()
        traj[a, :, :2] = xy
        path = torch.cat([past, xy])
        accel = (path[2:] - 2 * path[1:-1] + path[:-2]) / scene.dt**2
        smooth = accel.pow(2).mean()
        loss = ds.torch.cost(script, scene, traj) + 0.05 * smooth
        loss.backward()
        opt.step()
        if it % 100 == 0:
            print(f"step {it:3d}: loss {loss.item():.4f}")

    out = log.copy()
    out[a, :, :2] = xy.detach().numpy()
    after = script.evaluate(scene, out)
    print(f"optimised: total {after.total:.4f}  " + "  ".join(f"{k} {v:.3f}" for k, v in after.terms.items()))
    verdict = ds.check("cut_in", scene, out, PARAMS)
    print("checker on the optimised trajectories:", verdict)
    moved = np.nanmax(np.abs(out[:, :, :2] - log[:, :, :2]))
    print(f"largest move {moved:.2f} m; {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
