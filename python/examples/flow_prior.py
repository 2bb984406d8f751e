"""Bring your own model: a small PyTorch flow-matching prior over futures, guided by a Rhai
script through ds.torch.cost, judged by drivescript's checker.

1. Windows from data/samples: each agent's 1 s of history and 4 s of future, in its own frame
   (origin at its current position, x along its heading).
2. A rectified-flow MLP trained for about 30 seconds to generate the future from the history.
3. Futures of the cutter (US-101, agent 401) sampled from the prior, unguided and guided by
   scripts/cut_in.rhai: at each Euler step the predicted end of the flow is scored by the
   script, with every other agent on its log, and the flow moves against the gradient.
4. `cut_in`'s checker (the one `simulate --auto` uses) judges every sample.

What it shows is the plumbing, not a good prior: guidance lowers the script's cost (one run
on 2 shared cores: median 178 unguided, 23 guided), but a 30-second MLP over 461 windows
gives no sample the checker passes, guided or not (docs/python.md): they end beside the
victim's lane or short of getting ahead of the victim.

Run from the repository root: python python/examples/flow_prior.py [--seconds 30] [--device cuda]
(the model trains and samples on --device; drivescript scores its samples on the CPU and hands
the gradient back on the model's device).
"""

import argparse
import math
import pathlib
import time

import numpy as np
import torch

import drivescript as ds

ROOT = pathlib.Path(__file__).resolve().parents[2]
HIST, FUT = 10, 40
SCALE = 40.0  # metres: futures are learnt divided by this
PARAMS = {"cutter": 401, "victim": 405}


def to_frame(points, origin, heading):
    """World points [..., 2] into the frame at `origin` facing `heading`."""
    c, s = math.cos(heading), math.sin(heading)
    d = points - origin
    return np.stack([c * d[..., 0] + s * d[..., 1], -s * d[..., 0] + c * d[..., 1]], axis=-1)


def windows(device):
    """(history, future) pairs in each agent's frame from every CommonRoad sample."""
    hist, fut = [], []
    for path in sorted((ROOT / "data/samples/commonroad").glob("*.xml")):
        # Current step 0: log_history is the first state, log_future the rest of the recording.
        scene = ds.Scene.load(path, commonroad_current_step=0)
        full = np.concatenate([scene.log_history(), scene.log_future()], axis=1)
        for a in range(full.shape[0]):
            for c in range(HIST, full.shape[1] - FUT):
                w = full[a, c - HIST : c + FUT + 1]
                if np.isnan(w).any():
                    continue
                origin, heading = w[HIST, :2], w[HIST, 2]
                xy = to_frame(w[:, :2], origin, heading)
                hist.append(xy[:HIST].ravel())
                fut.append(xy[HIST + 1 :].ravel())
    return (
        torch.tensor(np.array(hist), dtype=torch.float32, device=device) / SCALE,
        torch.tensor(np.array(fut), dtype=torch.float32, device=device) / SCALE,
    )


class Flow(torch.nn.Module):
    """Velocity field v(x_t, t | history) of a rectified flow from noise to futures."""

    def __init__(self, width=256):
        super().__init__()
        self.net = torch.nn.Sequential(
            torch.nn.Linear(2 * FUT + 1 + 2 * HIST, width),
            torch.nn.SiLU(),
            torch.nn.Linear(width, width),
            torch.nn.SiLU(),
            torch.nn.Linear(width, width),
            torch.nn.SiLU(),
            torch.nn.Linear(width, 2 * FUT),
        )

    def forward(self, x, t, cond):
        return self.net(torch.cat([x, t, cond], dim=1))


def train(model, hist, fut, seconds):
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
    start, step = time.perf_counter(), 0
    while time.perf_counter() - start < seconds:
        i = torch.randint(0, len(fut), (256,), device=fut.device)
        x1, cond = fut[i], hist[i]
        x0 = torch.randn_like(x1)
        t = torch.rand(len(i), 1, device=fut.device)
        loss = (model(x0 + t * (x1 - x0), t, cond) - (x1 - x0)).pow(2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % 500 == 0:
            print(f"  step {step:5d}: loss {loss.item():.4f}")
        step += 1
    return step


def sample(model, scene, script, cond, origin, heading, k, guidance, steps=20, seed=0):
    """k futures of the cutter, world frame [k, FUT, 3], guided when `guidance` > 0."""
    a = scene.agent_ids.index(PARAMS["cutter"])
    dev = cond.device
    log = torch.tensor(scene.log_future(FUT), device=dev)
    c, s = math.cos(heading), math.sin(heading)
    rot = torch.tensor([[c, -s], [s, c]], dtype=torch.float64, device=dev)
    org = torch.tensor(origin, dtype=torch.float64, device=dev)
    # Noise drawn on the CPU: the same seed gives the same starting points on every device.
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(k, 2 * FUT, generator=g).to(dev)
    cond = cond.expand(k, -1)

    def world(x1):
        xy = (x1.double().reshape(k, FUT, 2) * SCALE) @ rot.T + org
        prev = torch.cat([org.expand(k, 1, 2), xy[:, :-1]], dim=1)
        d = xy - prev
        h = torch.atan2(d[..., 1], d[..., 0])
        return torch.cat([xy, h.unsqueeze(-1)], dim=2)

    for n in range(steps):
        t = torch.full((k, 1), n / steps, device=dev)
        with torch.no_grad():
            v = model(x, t, cond)
        if guidance > 0:
            x1 = (x + (1 - t) * v).detach().requires_grad_(True)
            traj = log.expand(k, -1, -1, -1).clone()
            traj[:, a] = world(x1)
            ds.torch.cost(script, scene, traj).sum().backward()
            v = v - guidance * x1.grad.clamp(-1, 1)
        x = x + v / steps
    with torch.no_grad():
        return world(x).cpu().numpy()


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="training time")
    parser.add_argument("--samples", type=int, default=8)
    parser.add_argument("--guidance", type=float, default=2.0)
    parser.add_argument("--threads", type=int, default=1, help="PyTorch threads")
    parser.add_argument("--device", default="cpu", help="PyTorch device for the model (cpu, cuda, ...)")
    args = parser.parse_args()
    device = torch.device(args.device)
    # The model is small: one thread trains it fastest, and on a busy machine several spin
    # against each other (2 threads: 2.4 steps/s, 1 thread: 238, on 2 shared cores).
    torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    t0 = time.perf_counter()
    hist, fut = windows(device)
    print(f"{len(fut)} windows of {HIST} history and {FUT} future steps from data/samples")
    model = Flow().to(device)
    steps = train(model, hist, fut, args.seconds)
    print(f"trained {steps} steps in {args.seconds:.0f} s on {device}")

    scene = ds.Scene.load(ROOT / "data/samples/commonroad/USA_US101-4_1_T-1.xml")
    script = ds.CostScript.from_file(ROOT / "scripts/cut_in.rhai", params=PARAMS)
    a = scene.agent_ids.index(PARAMS["cutter"])
    past = scene.log_history()[a]
    origin, heading = past[-1, :2], past[-1, 2]
    cond = torch.tensor(to_frame(past[-HIST:, :2], origin, heading).ravel(), dtype=torch.float32, device=device) / SCALE
    log = scene.log_future(FUT)
    for name, g in [("unguided", 0.0), ("guided", args.guidance)]:
        cutter = sample(model, scene, script, cond.unsqueeze(0), origin, heading, args.samples, g)
        passed, achieved, totals = 0, 0, []
        for k in range(args.samples):
            traj = log.copy()
            traj[a] = cutter[k]
            totals.append(script.evaluate(scene, traj).total)
            verdict = ds.check("cut_in", scene, traj, PARAMS)
            passed += verdict.passed
            achieved += verdict.achieved
            print(f"  {name} sample {k}: {verdict.reason}")
        print(f"{name}: {passed}/{args.samples} samples pass the cut_in checker ({achieved} reach "
              f"the cut-in's geometry); cut_in cost median {np.median(totals):.3f}")
    print(f"{time.perf_counter() - t0:.1f} s in all")


if __name__ == "__main__":
    main()
