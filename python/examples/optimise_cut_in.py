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

    # Positions are the variables; headings follow the direction of travel.
    xy = torch.tensor(log[:, :, :2], requires_grad=True)
    heading = torch.tensor(log[:, :, 2:])
    opt = torch.optim.Adam([xy], lr=0.05)
    for it in range(301):
        opt.zero_grad()
        traj = torch.cat([xy, heading], dim=2)
        # A little smoothness in PyTorch beside the script: costs compose as tensors.
        accel = xy[:, 2:] - 2 * xy[:, 1:-1] + xy[:, :-2]
        smooth = torch.nan_to_num(accel).pow(2).sum()
        loss = ds.torch.cost(script, scene, traj) + 10.0 * smooth
        loss.backward()
        opt.step()
        if it % 50 == 0:
            print(f"step {it:3d}: loss {loss.item():.4f}")

    out = torch.cat([xy, heading], dim=2).detach().numpy()
    after = script.evaluate(scene, out)
    print(f"optimised: total {after.total:.4f}  " + "  ".join(f"{k} {v:.3f}" for k, v in after.terms.items()))
    verdict = ds.check("cut_in", scene, out, PARAMS)
    print("checker on the optimised trajectories:", verdict)
    moved = np.nanmax(np.abs(out[:, :, :2] - log[:, :, :2]))
    print(f"largest move {moved:.2f} m; {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
