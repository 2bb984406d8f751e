"""How far a checkpoint's unguided samples stray from the lanes of the windows they are drawn
in, against the recorded futures: a check of the network alone, in seconds, with no guidance,
no planner and no map geometry beyond the lane centre lines the network itself is shown.

For windows of a `drivescript train --export` directory, each agent with a fully observed
future: the largest distance, over its 80 future points, to the nearest lane centre line of the
window (the polylines of the window's own encoding, 20 points a lane). It prints the fraction of agents
whose future goes more than --far metres from every lane point and the median of that largest
distance, for the recorded futures (decoded from their PCA coefficients) and for samples of the
PyTorch port's Heun sampler (`denoiser.py`, which matches drivescript's to 1e-6). The nearest
lane's distance saturates near half a lane width (past it the next lane's centre line is
nearer), so it also prints the fraction of agents that come more than 1.75 m from every lane
their recorded future follows (within 1 m of it), and that median: a sample that takes another
legal route counts as off its route there. With
`--from-log`, it also starts the sampler from the recorded future plus noise of each level:
where lanes are lost between the log and pure noise. With `--split SIGMA...`, one denoising
step from the recorded future plus noise of each level, its error (and the noise's) split into
the part along the recorded path and the part across it (RMS over the future points, metres):
whether the network removes noise across the lane as it does along it.

    python3 benches/torch/lanes.py EXPORT_DIR CHECKPOINT... [--file train-00010.safetensors]
        [--from-log] [--from-noise SIGMA...] [--split SIGMA...]
"""

import argparse
import json
import os
import sys

import torch
from safetensors.torch import load_file

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from denoiser import Denoiser  # noqa: E402

CTX = ["lane_points", "lane_mask", "lane_rel", "lane_conn", "agent_hist", "agent_mask",
       "agent_lane_rel", "agent_rel", "agent_attr"]
POS_SCALE, REL_SCALE = 10.0, 50.0  # src/train/batch.rs


def schedule(edm, n):
    """src/model/edm.rs, Edm::schedule."""
    a, b = edm["sigma_max"] ** (1 / edm["rho"]), edm["sigma_min"] ** (1 / edm["rho"])
    return [(a + i / (max(n, 2) - 1) * (b - a)) ** edm["rho"] for i in range(n)] + [0.0]


def advance(hist, history):
    """Window::advance: metres a step along the heading over up to 4 observed history steps,
    from the agents' history features `[B, N, history, 4]` (own frame, /POS_SCALE)."""
    b, n = hist.shape[:2]
    out = torch.zeros(b, n, dtype=torch.float64)
    observed = hist[..., 3] > 0
    for i in range(b):
        for a in range(n):
            m = 0
            while m < 4 and m + 1 < history and observed[i, a, history - 2 - m]:
                m += 1
            if m:
                dx = hist[i, a, history - 1, 0] - hist[i, a, history - 1 - m, 0]
                out[i, a] = dx.item() * POS_SCALE / m
    return out


def decode(meta, coeffs, adv, route=None):
    """Normaliser::decode plus the constant-velocity anchor: positions `[B, N, F, 2]` in each
    agent's own frame. A checkpoint that tells futures against lane routes (`route_frame`)
    needs the windows' `agent_route` ([`from_route`])."""
    norm = meta["normaliser"]
    pca = norm["pca"]
    comps = torch.tensor(pca["components"], dtype=torch.float64).reshape(-1, pca["dim"])
    mean = torch.tensor(pca["mean"], dtype=torch.float64)
    scale = torch.tensor(norm["std"], dtype=torch.float64) / norm["sigma_data"]
    v = ((coeffs.double() * scale) @ comps + mean).reshape(*coeffs.shape[:-1], -1, 3).clone()
    v[..., 0] += adv[..., None] * torch.arange(1, v.shape[-2] + 1, dtype=torch.float64)
    if meta["config"]["window"].get("route_frame", False):
        return from_route(v, route)
    return v[..., :2]


def from_route(v, route):
    """src/scene/routes.rs, from_route_residual, for futures `v` `[B, N, F, 3]` (along with the
    anchor added, across, heading) on the route as the network reads it (`agent_route`, 16
    points 5 m apart from where the agent projects onto its route): straight segments between
    those points, continued straight past both ends. It matches drivescript's path to the
    corners' smoothing within the 75 m the points cover; past them drivescript's route goes on
    with its lanes where this one goes straight. An agent without a route (all points zero)
    is decoded along its heading."""
    b, n = v.shape[:2]
    q = route.double().reshape(b, n, -1, 2) * REL_SCALE
    p = q.shape[2]
    seg = q[:, :, 1:] - q[:, :, :-1]
    ln = seg.norm(dim=-1)
    has = ln[..., 0] > 1e-6
    unit = seg / ln.clamp(min=1e-9)[..., None]
    cum = torch.cat([torch.zeros(b, n, 1, dtype=ln.dtype), ln.cumsum(-1)], -1)
    t0 = unit[:, :, 0]
    # The agent (the origin) left of the route's first point: d0.
    d0 = t0[..., 1] * q[:, :, 0, 0] - t0[..., 0] * q[:, :, 0, 1]
    u, d = v[..., 0], d0[..., None] + v[..., 1]
    i = (torch.searchsorted(cum.contiguous(), u.contiguous(), right=True) - 1).clamp(0, p - 2)
    start = q.gather(2, i[..., None].expand(-1, -1, -1, 2))
    dirn = unit.gather(2, i[..., None].expand(-1, -1, -1, 2))
    along = (u - cum.gather(2, i))[..., None]
    normal = torch.stack([-dirn[..., 1], dirn[..., 0]], -1)
    pos = start + dirn * along + normal * d[..., None]
    return torch.where(has[..., None, None], pos, v[..., :2])


def lanes_in_agent_frames(ctx):
    """Every lane point in every agent's frame, `[B, N, M, P]` x and y."""
    rel = ctx["agent_lane_rel"].double()
    c, s = rel[..., 2:3], rel[..., 3:4]
    lx, ly = rel[..., 0:1] * REL_SCALE, rel[..., 1:2] * REL_SCALE
    p = ctx["lane_points"].double()[:, None] * POS_SCALE
    return lx + c * p[..., 0] - s * p[..., 1], ly + s * p[..., 0] + c * p[..., 1]


def per_lane(traj, lanes, lane_mask):
    """Per window, the distance of every future point to every lane `[N, F, M]` (to the
    segments between consecutive lane points, since a long lane's 20 points lie tens of metres
    apart; infinite for padding). One window at a time, to bound memory."""
    lx, ly = lanes
    out = []
    for i in range(traj.shape[0]):
        ax, ay = lx[i][:, None, :, :-1], ly[i][:, None, :, :-1]  # [N, 1, M, P-1]
        dx, dy = lx[i][:, None, :, 1:] - ax, ly[i][:, None, :, 1:] - ay
        px, py = traj[i][..., 0][..., None, None], traj[i][..., 1][..., None, None]  # [N, F, 1, 1]
        t = (((px - ax) * dx + (py - ay) * dy) / (dx * dx + dy * dy).clamp(min=1e-9)).clamp(0, 1)
        d = ((px - ax - t * dx) ** 2 + (py - ay - t * dy) ** 2).sqrt().min(-1).values  # [N, F, M]
        keep = lane_mask[i][None, None, :] > 0
        out.append(torch.where(keep, d, torch.full_like(d, float("inf"))))
    return out


def stray(d, full, route=None):
    """Per counted agent, the largest distance of a future point to the nearest lane, or to
    the nearest of its route's lanes (`route`, per window `[N, M]`)."""
    out = []
    for i, di in enumerate(d):
        if route is not None:
            di = torch.where(route[i][:, None, :], di, torch.full_like(di, float("inf")))
        out.append(di.min(-1).values.max(-1).values)  # [N]
    return torch.stack(out)[full]


def along_across(err, path):
    """RMS of `err` `[A, F, 2]` along and across `path` `[A, F, 2]` (the direction of travel
    from each point to the next; the last point takes its predecessor's; a standing agent,
    its own x axis)."""
    t = torch.zeros_like(path)
    t[:, :-1] = path[:, 1:] - path[:, :-1]
    t[:, -1] = t[:, -2]
    norm = t.norm(dim=-1, keepdim=True)
    t = torch.where(norm > 1e-3, t / norm.clamp(min=1e-9), torch.tensor([1.0, 0.0], dtype=t.dtype))
    along = (err * t).sum(-1)
    across = err[..., 0] * -t[..., 1] + err[..., 1] * t[..., 0]
    return along.pow(2).mean().sqrt().item(), across.pow(2).mean().sqrt().item()


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", help="a `drivescript train --export` directory")
    ap.add_argument("checkpoints", nargs="+")
    ap.add_argument("--file", default="train-00010.safetensors", help="which file of windows")
    ap.add_argument("--windows", type=int, default=64)
    ap.add_argument("--steps", type=int, default=32, help="Heun steps")
    ap.add_argument("--far", type=float, default=4.0, help="metres from every lane")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--from-log", action="store_true")
    ap.add_argument("--from-noise", type=float, nargs="*", default=[], metavar="SIGMA",
                    help="also sample from pure noise of these levels, the schedule cut to them: "
                         "whether the levels above, where training rarely draws its noise, "
                         "are where the lanes are lost")
    ap.add_argument("--split", type=float, nargs="*", default=[], metavar="SIGMA",
                    help="one denoising step from the recorded future plus noise of these levels: "
                         "its error along and across the recorded path")
    a = ap.parse_args()
    win = load_file(os.path.join(a.data, a.file))
    win["lane_conn"] = win["lane_conn"].long()
    g = torch.Generator().manual_seed(a.seed)
    idx = torch.randperm(win["target"].shape[0], generator=g)[:a.windows]
    ctx = {k: win[k][idx] for k in CTX + ["agent_route"] if k in win}
    route_in = ctx.get("agent_route")
    target, mask, seen = win["target"][idx], win["loss_mask"][idx], win["seen"][idx]
    b, n, _ = target.shape
    lanes = lanes_in_agent_frames(ctx)
    full = seen.reshape(b, n, -1, 3).bool().all(-1).all(-1) & (mask > 0)
    print(f"{a.file}: {b} windows, {int(full.sum())} agents with a whole future")

    route = None

    def row(name, meta, coeffs, adv):
        nonlocal route
        d = per_lane(decode(meta, coeffs, adv, route_in), lanes, ctx["lane_mask"])
        if route is None:
            # The lanes the recorded future follows: those it comes within 1 m of. The nearest
            # lane alone cannot tell a car half a lane over from one on the next lane, since
            # past 1.75 m the next lane's centre line is nearer.
            route = [di.min(1).values <= 1.0 for di in d]
        w, r = stray(d, full), stray(d, full, route)
        print(f"  {name:<32} beyond {a.far:g} m: {(w > a.far).double().mean().item():.3f}   "
              f"median largest distance {w.median().item():.2f} m   off its route's lanes by "
              f"over 1.75 m: {(r > 1.75).double().mean().item():.3f}, median "
              f"{r.median().item():.2f} m", flush=True)
        # How far from the recorded future itself: a network that learnt these windows gives
        # them back, whatever the lanes.
        gap = (decode(meta, coeffs, adv, route_in) - decode(meta, target, adv, route_in)).norm(dim=-1)[full]
        cols = []
        for sec in (1, 2, 4, 8):
            if 10 * sec <= gap.shape[-1]:
                g_ = gap[:, 10 * sec - 1]
                cols.append(f"{sec} s {g_.median().item():.2f} / {g_.quantile(0.9).item():.2f}")
        print(f"  {'':<32} from the recorded future, median / 90th percentile (m): "
              + ", ".join(cols), flush=True)

    for ck in a.checkpoints:
        with open(os.path.join(ck, "config.json")) as f:
            meta = json.load(f)
        history = meta["config"]["window"]["history"]
        hist = ctx["agent_hist"].reshape(b, n, history, 4)
        adv = advance(hist, history)
        model = Denoiser(ck)
        print(ck)
        row("recorded future", meta, target, adv)
        sig = schedule(meta["config"]["edm"], a.steps)
        starts = [(None, sig)]
        if a.from_log:
            starts += [(s, [x for x in sig if x <= s]) for s in (0.3, 1.0, 3.0, 10.0)]
        for start, sg in starts:
            torch.manual_seed(a.seed + 4)
            with torch.no_grad():
                x0 = torch.randn(target.shape) * sg[0]
                if start is not None:
                    x0 = x0 + target
                out = model.sample(ctx, x0, sg)
            name = "sample" if start is None else f"recorded + noise {sg[0]:.2f}"
            row(name, meta, out, adv)
        if a.split:
            enc = model.encode_map(ctx)
            path = decode(meta, target, adv, route_in)[full]
        for s in a.split:
            torch.manual_seed(a.seed + 5)
            with torch.no_grad():
                noisy = target + torch.randn(target.shape) * s
                den = model.denoise(ctx, enc, noisy, s)
            na, nc = along_across(decode(meta, noisy, adv, route_in)[full] - path, path)
            da, dc = along_across(decode(meta, den, adv, route_in)[full] - path, path)
            print(f"  one step from recorded + noise {s:<6g} noise along {na:7.2f} m across "
                  f"{nc:7.2f} m   denoised along {da:6.2f} m across {dc:6.2f} m", flush=True)
        for s in a.from_noise:
            sg = [x for x in sig if x <= s]
            torch.manual_seed(a.seed + 4)
            with torch.no_grad():
                out = model.sample(ctx, torch.randn(target.shape) * sg[0], sg)
            row(f"noise alone from {sg[0]:.2f}", meta, out, adv)


if __name__ == "__main__":
    main()
