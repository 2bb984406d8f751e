"""The three costs of `drivescript bench cost` written in PyTorch, checked against drivescript
and timed beside it.

`scripts/cut_in.rhai`, `scripts/rightmost_lane.rhai` and `scripts/no_collisions.rhai` are
ported the way a PyTorch user writes a cost: float64 tensors over every agent and step at once,
no Python loop over steps or pairs, and autograd for the gradient. What is not differentiable
comes from drivescript's map through the Python package, as a port to another framework would
get it: the agents' sizes and types (`Scene.agent_sizes`, `Scene.agent_types`), the centre lines
Frenet coordinates are measured on (`Scene.agent_lane_path`, `Scene.lane_path`), and
rightmost_lane's choice of target lane (the script's own lines, run once, print it).

The geometry follows drivescript's definitions, so that values agree to rounding:

- Frenet coordinates (src/geom/frenet.rs): every vertex gets the bisector of its segments'
  normals, normals are interpolated along each segment, and a point maps to the parameter t
  where it lies on the interpolated normal line (a root of a quadratic per segment); the path
  continues straight past its ends; among the roots on segments within twice the nearest
  segment's distance the one with the smallest |d| is taken. The choice is made without
  gradient; t, s and d are then recomputed from the chosen segment with autograd, which gives
  the implicit-function derivative drivescript uses.
- Box clearance (src/cost/fwd.rs): apart, the smallest of the 32 vertex-to-edge distances;
  overlapping, minus the smallest overlap along the four box axes.

Run from the repository root with the package importable and `target/release/drivescript`
built (the `bench cost` rows are timed by running it):

    python benches/torch/costs.py [--rounds 7] [--seconds 1] [--threads 1]

It prints the largest differences in value and gradient against `CostScript.evaluate`, then
times, interleaved round by round: drivescript from Python (`CostScript.evaluate`, value and
gradient), the `drivescript bench cost` rows (a separate process), PyTorch eager forward +
backward, and `torch.compile`d forward + backward (after warm-up), and prints medians over the
rounds and the ratios.
"""

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pathlib  # noqa: E402
import re  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

import drivescript as ds  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[2]
SHARED = ROOT / "../shared/data/commonroad-ngsim/USA_US101-23_1_T-1.xml.gz"
SAMPLE = ROOT / "data/samples/commonroad/USA_US101-4_1_T-1.xml"
NAMES = ["cut_in", "rightmost_lane", "no_collisions"]
F64 = torch.float64


def relu(x):
    return torch.clamp(x, min=0.0)


# --- Frenet coordinates on a polyline -------------------------------------------------------


def cross(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


class Path:
    """A centre line as drivescript's FrenetPath sees it, as tensors: segments as pieces with
    interpolated normals, and the straight extensions before the start and after the end."""

    def __init__(self, points):
        p = torch.as_tensor(points, dtype=F64)
        e = p[1:] - p[:-1]
        length = torch.linalg.norm(e, dim=1)
        unit = e / length[:, None]
        seg_n = torch.stack([-unit[:, 1], unit[:, 0]], dim=1)
        bis = seg_n[:-1] + seg_n[1:]
        bn = torch.linalg.norm(bis, dim=1, keepdim=True)
        # A hairpin has no bisector: the incoming normal there.
        inner = torch.where(bn < 1e-6, seg_n[:-1], bis / bn.clamp(min=1e-300))
        normals = torch.cat([seg_n[:1], inner, seg_n[-1:]])
        cum = torch.cat([torch.zeros(1, dtype=F64), torch.cumsum(length, 0)])
        total = cum[-1]
        inf = torch.tensor([float("inf")], dtype=F64)
        # Pieces: 0 is before the start, 1 after the end, 2.. the segments.
        self.a = torch.cat([p[:1], p[-1:], p[:-1]])
        self.e = torch.cat([unit[:1], unit[-1:], e])
        self.n0 = torch.cat([normals[:1], normals[-1:], normals[:-1]])
        self.n1 = torch.cat([normals[:1], normals[-1:], normals[1:]])
        self.s0 = torch.cat([torch.zeros(1, dtype=F64), total[None], cum[:-1]])
        self.scale = torch.cat([torch.ones(2, dtype=F64), length])
        self.t_min = torch.cat([-inf, torch.zeros(1, dtype=F64), torch.zeros(len(e), dtype=F64)])
        self.t_max = torch.cat([torch.zeros(1, dtype=F64), inf, torch.ones(len(e), dtype=F64)])
        self.seg_a, self.seg_e = p[:-1], e

    def _roots(self, q, a, b, c, t_min, t_max):
        """Both roots of a t² + b t + c (drivescript's numerically stable form; one root where
        the quadratic is linear), NaN where there is none inside [t_min, t_max]."""
        linear = a.abs() <= 1e-12 * (b.abs() + c.abs()).clamp(min=1e-300)
        disc = b * b - 4.0 * a * c
        sq = torch.sqrt(disc.clamp(min=0.0))
        sgn = torch.where(b >= 0, 1.0, -1.0).to(F64)
        qq = -0.5 * (b + sgn * sq)
        safe_a = torch.where(linear | (a == 0), 1.0, a)
        safe_qq = torch.where(qq == 0, 1.0, qq)
        safe_b = torch.where(b == 0, 1.0, b)
        r0 = torch.where(linear, -c / safe_b, torch.where(qq == 0, 0.0, qq / safe_a))
        r1 = torch.where(linear | (qq == 0), float("nan"), c / safe_qq)
        none = (linear & (b == 0)) | (~linear & (disc < 0))
        out = []
        for r in (r0, r1):
            ok = ~none & torch.isfinite(r) & (r >= t_min - 1e-9) & (r <= t_max + 1e-9)
            out.append((torch.where(ok, torch.clamp(r, min=t_min, max=t_max), float("nan")), ok))
        return out

    def project(self, xy):
        """s and d of points `xy` [..., 2], differentiable w.r.t. `xy`."""
        shape = xy.shape[:-1]
        pts = xy.reshape(-1, 2)
        with torch.no_grad():
            p = pts.detach()[:, None, :]
            # Point-to-segment distances: the candidates are the segments within twice the
            # nearest one's distance, and both extensions.
            w = p - self.seg_a
            el = (self.seg_e * self.seg_e).sum(-1)
            u = ((w * self.seg_e).sum(-1) / el).clamp(0.0, 1.0)
            dist = torch.linalg.norm(w - u[..., None] * self.seg_e, dim=-1)
            reach = 2.0 * dist.min(dim=1, keepdim=True).values + 1e-6
            cand = torch.cat([torch.ones_like(dist[:, :2], dtype=torch.bool), dist <= reach], dim=1)
            m = self.n1 - self.n0
            q = p - self.a
            a = -cross(self.e, m).expand(q.shape[:-1])
            b = cross(q, m) - cross(self.e, self.n0)
            c = cross(q, self.n0)
            best = torch.full(q.shape[:-1], float("inf"), dtype=F64)
            which = torch.zeros(q.shape[:-1], dtype=torch.long)
            for k, (t, ok) in enumerate(self._roots(q, a, b, c, self.t_min, self.t_max)):
                n = self.n0 + (self.n1 - self.n0) * t[..., None]
                r = q - self.e * t[..., None]
                d = ((r * n).sum(-1) / torch.linalg.norm(n, dim=-1).clamp(min=1e-12)).abs()
                d = torch.where(ok & cand, d, float("inf"))
                better = d < best
                best = torch.where(better, d, best)
                which = torch.where(better, k, which)
            # The piece with the smallest |d|, first among equals (drivescript keeps the first).
            piece = best.argmin(dim=1)
            root = which.gather(1, piece[:, None])[:, 0]
            if not torch.isfinite(best.min(dim=1).values).all():
                raise RuntimeError("a point past every normal line: not ported (drivescript's orthogonal fallback)")
        # The chosen piece's root again, now with autograd: t(p) and its derivative.
        A, E, N0, N1 = self.a[piece], self.e[piece], self.n0[piece], self.n1[piece]
        M = N1 - N0
        Q = pts - A
        a = -cross(E, M)
        b = cross(Q, M) - cross(E, N0)
        c = cross(Q, N0)
        (t0, _), (t1, _) = self._roots(Q, a, b, c, self.t_min[piece], self.t_max[piece])
        t = torch.where(root == 0, t0, t1)
        n = N0 + M * t[:, None]
        d = ((Q - E * t[:, None]) * n).sum(-1) / torch.linalg.norm(n, dim=-1).clamp(min=1e-12)
        s = self.s0[piece] + self.scale[piece] * t
        return s.reshape(shape), d.reshape(shape)


# --- Box clearance --------------------------------------------------------------------------


def corners(xyh, size):
    """x and y [..., 4] of the corners of boxes (counter-clockwise) and their unit axes
    ((ux, uy), (vx, vy)). Coordinates are kept apart rather than in a trailing dimension of 2:
    reductions over such a small dimension are slow in PyTorch."""
    c, s = torch.cos(xyh[..., 2]), torch.sin(xyh[..., 2])
    hl, hw = 0.5 * size[..., 0], 0.5 * size[..., 1]
    sign_l = torch.tensor([-1.0, 1.0, 1.0, -1.0], dtype=F64)
    sign_w = torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=F64)
    lx, ly = (hl * c)[..., None] * sign_l, (hl * s)[..., None] * sign_l
    wx, wy = (-hw * s)[..., None] * sign_w, (hw * c)[..., None] * sign_w
    x = xyh[..., 0:1] + lx + wx
    y = xyh[..., 1:2] + ly + wy
    return x, y, ((c, s), (-s, c))


def point_segment(px, py, ax, ay, bx, by):
    ex, ey = bx - ax, by - ay
    t = (((px - ax) * ex + (py - ay) * ey) / (ex * ex + ey * ey)).clamp(0.0, 1.0)
    dx, dy = px - ax - t * ex, py - ay - t * ey
    return torch.sqrt(dx * dx + dy * dy)


def box_clearance(xa, sa, xb, sb):
    """Signed clearance of boxes (x, y, heading) [..., 3] with sizes (length, width) [..., 2]:
    their distance apart, minus the smallest overlap along the four axes when they overlap."""
    ax, ay, axes_a = corners(xa, sa)
    bx, by, axes_b = corners(xb, sb)
    nxt = [1, 2, 3, 0]
    # Apart: every corner of one box against every edge of the other ([..., corner, edge]).
    def vertex_edge(px, py, qx, qy):
        return point_segment(px[..., :, None], py[..., :, None], qx[..., None, :], qy[..., None, :],
                             qx[..., None, nxt], qy[..., None, nxt]).flatten(-2).min(-1).values
    apart = torch.minimum(vertex_edge(ax, ay, bx, by), vertex_edge(bx, by, ax, ay))
    # Overlapping: the overlap along each of the four axes (separating axes).
    over = []
    for ux, uy in axes_a + axes_b:
        pa = ax * ux[..., None] + ay * uy[..., None]
        pb = bx * ux[..., None] + by * uy[..., None]
        over.append(torch.minimum(pa.amax(-1) - pb.amin(-1), pb.amax(-1) - pa.amin(-1)))
    over = torch.stack(over, -1)
    inside = (over > 0).all(-1)
    return torch.where(inside, -over.amin(-1), apart)


# --- The three costs ------------------------------------------------------------------------


class Costs:
    """The scene's constants for the three ports."""

    def __init__(self, scene, victim, cutter, target_lane, gap=5.0, tol=0.5, margin=0.5):
        ids = scene.agent_ids
        self.v, self.c = ids.index(victim), ids.index(cutter)
        self.sizes = torch.as_tensor(scene.agent_sizes, dtype=F64)
        self.victim_path = Path(scene.agent_lane_path(victim))
        self.target_path = Path(scene.lane_path(target_lane, 500.0))
        self.dt = scene.dt
        self.gap, self.tol, self.margin = gap, tol, margin
        veh = [i for i, t in enumerate(scene.agent_types) if t == "vehicle"]
        pairs = [(i, j) for k, i in enumerate(veh) for j in veh[k + 1:]]
        self.pi = torch.tensor([p[0] for p in pairs])
        self.pj = torch.tensor([p[1] for p in pairs])
        reach = 0.5 * torch.hypot(self.sizes[:, 0], self.sizes[:, 1])
        self.near = reach[self.pi] + reach[self.pj] + margin

    def cut_in(self, x):
        a, b = x[self.c], x[self.v]
        sa, da = self.victim_path.project(a[:, :2])
        sb, db = self.victim_path.project(b[:, :2])
        half = 0.5 * (self.sizes[self.c, 0] + self.sizes[self.v, 0])
        held = b.detach()  # hold(b): the victim gets no gradient from the gap and contact terms
        starts_beside = relu(1.5 - da[0].abs())
        ends_in_lane = relu(da[-1].abs() - self.tol)
        ends_ahead = relu(self.gap - (sa[-1] - sb[-1].detach() - half))
        clear = box_clearance(a, self.sizes[self.c].expand(len(a), 2), held, self.sizes[self.v].expand(len(a), 2))
        no_contact = (relu(0.5 - clear) ** 2).sum()
        victim_keeps_lane = relu(db.abs() - self.tol).mean()
        return starts_beside + ends_in_lane + ends_ahead + 5.0 * no_contact + victim_keeps_lane

    def rightmost_lane(self, x):
        a = x[self.v]
        _, d = self.target_path.project(a[:, :2])
        steps, dt = d.shape[0], self.dt
        # f.d.window(STEPS * DT - 1, STEPS * DT): the steps from 1 s before the end to the end,
        # as drivescript rounds a time to a step (step k is (k + 1) dt after the current one).
        i0, i1 = (round((steps * dt - 1.0 - dt) / dt), round((steps * dt - dt) / dt))
        settled = relu(d[i0:i1 + 1].abs() - self.tol).mean()
        return relu(d[-1].abs() - self.tol) + 0.5 * settled

    def no_collisions(self, x):
        # no_collision_cost's broad phase: only pairs whose centres are within their
        # half-diagonals and the margin at a step can be closer than the margin.
        with torch.no_grad():
            dx = x[self.pi, :, 0] - x[self.pj, :, 0]
            dy = x[self.pi, :, 1] - x[self.pj, :, 1]
            pair, step = torch.nonzero(torch.sqrt(dx * dx + dy * dy) <= self.near[:, None], as_tuple=True)
        i, j = self.pi[pair], self.pj[pair]
        clear = box_clearance(x[i, step], self.sizes[i], x[j, step], self.sizes[j])
        return (relu(self.margin - clear) ** 2).sum()


def target_lane(scene, vehicle):
    """rightmost_lane's target lane: the script's own lines (not differentiable), run once."""
    src = (ROOT / "scripts/rightmost_lane.rhai").read_text()
    head = src.split("let f = a.frenet(")[0]
    probe = ds.CostScript.from_source(
        head + "print(target);\nterm(\"probe\", relu(abs(a.frenet(lane_path(target, 500)).d.last())));\n",
        params={"vehicle": vehicle},
    )
    return int(probe.evaluate(scene, scene.filled_future()).prints[0])


# --- Checks and timing ----------------------------------------------------------------------


def value_and_grad(fn, traj):
    x = torch.tensor(traj, dtype=F64, requires_grad=True)
    v = fn(x)
    v.backward()
    return v.item(), x.grad.numpy()


def rust_rows(cli, scene_path, seconds):
    out = subprocess.run(
        [cli, "bench", "cost", "--scene", str(scene_path), "--seconds", str(seconds)],
        capture_output=True, text=True, check=True,
    ).stdout
    rows = {}
    for line in out.splitlines():
        m = re.match(r"\|\s*([a-z_]+)\s*\|\s*([0-9.]+)\s*\|", line)
        if m and m.group(1) in NAMES:
            rows[m.group(1)] = float(m.group(2))
    if set(rows) != set(NAMES):
        raise SystemExit(f"`drivescript bench cost` printed no row for some of {NAMES}:\n{out}")
    return rows


def per_call_us(f, seconds):
    """Mean µs per call of `f` over a loop of at least `seconds` (as `bench cost` times)."""
    f()
    reps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds or reps < 3:
        f()
        reps += 1
    return (time.perf_counter() - start) / reps * 1e6


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--seconds", type=float, default=1.0, help="per timed loop and round")
    ap.add_argument("--threads", type=int, default=1, help="PyTorch's intra-op threads (drivescript's evaluate runs on one)")
    ap.add_argument("--scene", type=pathlib.Path, default=SHARED if SHARED.exists() else SAMPLE)
    ap.add_argument("--cli", default=os.environ.get("DRIVESCRIPT_BIN") or str(ROOT / "target/release/drivescript"))
    ap.add_argument("--no-compile", action="store_true", help="skip torch.compile")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    scene = ds.Scene.load(args.scene).crop(24, 80)
    traj = scene.filled_future()
    v, c = scene.agent_ids[0], scene.agent_ids[1]
    scripts = {
        "cut_in": ds.CostScript.from_file(ROOT / "scripts/cut_in.rhai", params={"cutter": c, "victim": v}),
        "rightmost_lane": ds.CostScript.from_file(ROOT / "scripts/rightmost_lane.rhai", params={"vehicle": v}),
        "no_collisions": ds.CostScript.from_file(ROOT / "scripts/no_collisions.rhai", params={"margin": 0.5}),
    }
    costs = Costs(scene, v, c, target_lane(scene, v))
    eager = {n: getattr(costs, n) for n in NAMES}
    print(f"scene {scene.scenario_id} ({args.scene}): {len(scene.agent_ids)} agents x {traj.shape[1]} steps, "
          f"victim {v}, cutter {c}; torch {torch.__version__}, {args.threads} thread(s); {os.cpu_count()} cores; "
          f"load {os.getloadavg()[0]:.1f}")

    # The bench's trajectories, and the same with seeded noise and the victim drifting 4 m
    # sideways over the horizon (so that rightmost_lane's terms, all 0 on the bench's, act).
    rng = np.random.default_rng(30)
    moved = traj + rng.normal(0.0, 1.0, traj.shape) * np.array([0.3, 0.3, 0.02])
    moved[0, :, 1] += np.linspace(0.0, 4.0, traj.shape[1])
    print("\n| cost | trajectories | drivescript value | PyTorch value | value rel. diff | max grad diff | max |grad| |")
    print("|---|---|---|---|---|---|---|")
    worst = 0.0
    for n in NAMES:
        for what, t in [("bench", traj), ("perturbed", moved)]:
            r = scripts[n].evaluate(scene, t)
            val, grad = value_and_grad(eager[n], t)
            rel = abs(val - r.total) / max(abs(r.total), abs(val), 1e-300)
            scale = max(np.abs(r.grad).max(), 1e-300)
            gd = np.abs(grad - r.grad).max()
            worst = max(worst, rel, gd / scale)
            print(f"| {n} | {what} | {r.total:.12g} | {val:.12g} | {rel:.1e} | {gd:.1e} | {np.abs(r.grad).max():.3g} |")
    print(f"largest relative difference (values, and gradients against their largest entry): {worst:.1e}")

    x = torch.tensor(traj, dtype=F64)

    def torch_step(fn):
        def step():
            xx = x.clone().requires_grad_(True)
            fn(xx).backward()
            return xx.grad
        return step

    compiled = {}
    if not args.no_compile:
        for n in NAMES:
            fn = torch.compile(eager[n])
            t0 = time.perf_counter()
            for _ in range(3):
                torch_step(fn)()
            compiled[n] = fn
            _, g = value_and_grad(fn, traj)
            print(f"torch.compile {n}: warm-up {time.perf_counter() - t0:.1f} s, "
                  f"max grad diff against eager {np.abs(g - value_and_grad(eager[n], traj)[1]).max():.1e}")

    cols = ["python", "bench", "eager"] + (["compiled"] if compiled else [])
    times = {n: {k: [] for k in cols} for n in NAMES}
    loads = []
    for _ in range(args.rounds):
        loads.append(os.getloadavg()[0])
        for n, us in rust_rows(args.cli, args.scene, args.seconds).items():
            times[n]["bench"].append(us)
        for n in NAMES:
            times[n]["python"].append(per_call_us(lambda: scripts[n].evaluate(scene, traj), args.seconds))
            times[n]["eager"].append(per_call_us(torch_step(eager[n]), args.seconds))
            if compiled:
                times[n]["compiled"].append(per_call_us(torch_step(compiled[n]), args.seconds))
    print(f"\n{args.rounds} interleaved rounds of {args.seconds} s per loop; medians, µs per value + gradient; "
          f"load (1 min) {min(loads):.1f} to {max(loads):.1f}")
    head = "| cost | drivescript `evaluate` (Python) | `bench cost` | PyTorch eager | eager / drivescript |"
    if compiled:
        head += " torch.compile | compiled / drivescript |"
    print(head)
    print("|---" * (head.count("|") - 1) + "|")
    for n in NAMES:
        m = {k: statistics.median(v) for k, v in times[n].items()}
        row = f"| {n} | {m['python']:.1f} | {m['bench']:.1f} | {m['eager']:.1f} | {m['eager'] / m['python']:.1f}x |"
        if compiled:
            row += f" {m['compiled']:.1f} | {m['compiled'] / m['python']:.1f}x |"
        print(row)


if __name__ == "__main__":
    main()
