"""Trajectory optimisation in plain PyTorch with a Rhai cost script.

The cutter's motion (US-101, agents 401 and 405) is optimised with Adam against
scripts/cut_in.rhai, whose gradient comes from the Rust engine through ds.torch.cost, beside
kinematic bounds written in PyTorch; the checker that `drivescript simulate --auto cut_in`
uses then judges the result: it passes (a cut-in, with no implausible motion). Run from the
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

    # The cutter's accelerations are the variables (everyone else keeps the log): its
    # velocities and positions integrate them from its recorded current state, and its
    # headings follow its velocity. The script says what should happen; how a car can move
    # is said beside it in PyTorch and composed with the script's cost as tensors compose:
    # speed and acceleration stay inside the checker's bounds (its sprint bound less 10 %,
    # its 7 m/s² less 35 %), and the ride is smooth.
    a = scene.agent_ids.index(PARAMS["cutter"])
    fixed = torch.tensor(log)
    hist = torch.tensor(scene.log_history()[a, :, :2])
    dt = scene.dt
    v_now = (hist[-1] - hist[-4]) / (3 * dt)  # over 0.3 s, as the checker reads the joint
    max_speed = 0.9 * min(40.0, 1.6 * float(v_now.norm()) + 8.0)
    max_accel = 0.65 * 7.0
    # Started from a firm push forward over the first 2 s: merging first and speeding up
    # after is a local minimum (the contact term holds a cutter that is behind the victim).
    accel = torch.zeros(log.shape[1], 2)
    accel[:20] = 3.0 * v_now / v_now.norm()
    accel.requires_grad_(True)

    def with_cutter(accel):
        vel = v_now + dt * torch.cumsum(accel, dim=0)
        traj = fixed.clone()
        traj[a, :, :2] = hist[-1] + dt * torch.cumsum(vel, dim=0)
        traj[a, :, 2] = torch.atan2(vel[:, 1], vel[:, 0])
        return traj, vel

    def kinematics(accel, vel):
        bounds = torch.relu(vel.norm(dim=1) - max_speed).pow(2).sum()
        bounds = bounds + torch.relu(accel.norm(dim=1) - max_accel).pow(2).sum()
        jerk = (accel[1:] - accel[:-1]) / dt
        return 10.0 * bounds + 1e-4 * jerk.pow(2).sum() + 1e-3 * accel.pow(2).sum()

    opt = torch.optim.Adam([accel], lr=0.2)
    for it in range(801):
        opt.zero_grad()
        traj, vel = with_cutter(accel)
        loss = ds.torch.cost(script, scene, traj) + kinematics(accel, vel)
        loss.backward()
        opt.step()
        if it % 100 == 0:
            print(f"step {it:3d}: loss {loss.item():.4f}")

    out = with_cutter(accel.detach())[0].numpy()
    after = script.evaluate(scene, out)
    print(f"optimised: total {after.total:.4f}  " + "  ".join(f"{k} {v:.3f}" for k, v in after.terms.items()))
    verdict = ds.check("cut_in", scene, out, PARAMS)
    print("checker on the optimised trajectories:", verdict)
    print("  violations:", verdict.violations or "none")
    v = np.linalg.norm(np.diff(out[a, :, :2], axis=0), axis=1) / scene.dt
    print(f"  cutter's speed {np.linalg.norm(v_now):.1f} m/s now, {v.max():.1f} m/s at most")
    moved = np.nanmax(np.abs(out[:, :, :2] - log[:, :, :2]))
    print(f"largest move {moved:.2f} m; {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
