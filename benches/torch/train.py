"""Trains drivescript's denoiser with PyTorch, on an accelerator, from windows that drivescript
cut and encoded (`drivescript train --export DIR --resume CHECKPOINT ...`), and writes a
drivescript checkpoint (model.safetensors + config.json) that `simulate` and `eval` load.

It follows src/train/trainer.rs step for step: the EDM loss over the observed future
coordinates through the loss basis, noise levels exp(P_mean + P_std z), AdamW (beta 0.9/0.999,
eps 1e-8, decoupled weight decay 1e-4), linear warm-up over the first 2 % then cosine decay to a
tenth of the rate, and a moving average of the weights (half-life in steps, with the same
early ramp) that the checkpoint samples with. It differs in what a GPU is for: larger batches,
and a run bounded by time (the schedule runs over --minutes, not a step count).

Before training it reproduces the export's loss check (`check.safetensors`: the loss
drivescript's own trainer computed for the first windows with the --check checkpoint) and
stops if it differs: a port that computes another loss would train another model.

    python3 benches/torch/train.py EXPORT_DIR OUT_DIR --check data/cities-wip --minutes 6
"""

import argparse
import glob
import json
import math
import os
import sys
import time

import torch
from safetensors.torch import load_file, save_file

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from denoiser import Denoiser  # noqa: E402

CTX = ["lane_points", "lane_mask", "lane_rel", "lane_conn", "agent_hist", "agent_mask",
       "agent_lane_rel", "agent_rel", "agent_attr"]
# src/model/denoiser.rs, ROUTE_FEATURES: (x, y) of 16 points of each agent's route ahead.
ROUTE_FEATURES = 32


def shapes(model, k):
    """Names and shapes of the network's variables (src/model/*.rs)."""
    d, hist, f = model["d"], model["history"], model["noise_freqs"]
    out = {"lanes.l1.weight": [d, 2], "lanes.l1.bias": [d], "lanes.l2.weight": [d, d],
           "lanes.l2.bias": [d], "lanes.l3.weight": [d, d], "lanes.l3.bias": [d],
           "agents.l1.weight": [d, hist * 4 + model.get("attrs", 0) + 2 * f + k
                                + (ROUTE_FEATURES if model.get("route_frame") else 0)],
           "agents.l1.bias": [d], "agents.l2.weight": [d, d], "agents.l2.bias": [d],
           "head1.weight": [d, d], "head1.bias": [d], "head2.weight": [k, d], "head2.bias": [k]}
    for i in range(model["layers"]):
        for block in ["lane_lane", "agent_lane", "agent_agent"]:
            p = f"{block}{i}."
            for lin in ["q", "o", "v", "rv2"]:
                out[p + lin + ".weight"], out[p + lin + ".bias"] = [d, d], [d]
            out[p + "k.weight"], out[p + "rk2.weight"] = [d, d], [d, d]
            rel = model.get("agent_lane_features", 4) if block == "agent_lane" else 4
            for lin in ["rk1", "rv1"]:
                out[p + lin + ".weight"], out[p + lin + ".bias"] = [d, rel], [d]
            out[p + "ff1.weight"], out[p + "ff1.bias"] = [2 * d, d], [2 * d]
            out[p + "ff2.weight"], out[p + "ff2.bias"] = [d, 2 * d], [d]
            for ln in ["ln1", "ln2", "ln_kv", "ln_q"]:
                out[p + ln + ".weight"], out[p + ln + ".bias"] = [d], [d]
            out[p + "ln_k.weight"], out[p + "ln_r.weight"] = [d], [d]
            if block == "lane_lane":
                out[p + "conn.weight"] = [5, d]
    return out


def fresh(model, k, gen):
    """src/train/trainer.rs, seeded_init: matrices N(0, 1/fan_in), the output layer zero,
    norm gains one, biases zero."""
    w = {}
    for name, dims in shapes(model, k).items():
        if name.startswith("head2."):
            w[name] = torch.zeros(dims)
        elif len(dims) == 1:
            one = ".ln" in name and name.endswith("weight")
            w[name] = torch.ones(dims) if one else torch.zeros(dims)
        else:
            w[name] = torch.randn(dims, generator=gen) / math.sqrt(dims[-1])
    return w


def checkpoint_weights(ck):
    """The weights a run resumes from: the online ones where a moving average is saved."""
    online = os.path.join(ck, "online.safetensors")
    return load_file(online if os.path.exists(online) else os.path.join(ck, "model.safetensors"))


def load_windows(data, kind, dev):
    files = sorted(glob.glob(os.path.join(data, f"{kind}-*.safetensors")))
    if not files:
        return None
    parts = [load_file(f) for f in files]
    out = {key: torch.cat([p[key] for p in parts]).to(dev) for key in parts[0]}
    out["lane_conn"] = out["lane_conn"].long()
    return out


def loss(model, edm, win, basis, idx, sigma, noise, per_component_weight=False):
    """src/train/trainer.rs, `loss`. With per-component spreads, the weight is still the one
    `sigma_data`'s, so that an error counts by its metres, unless `per_component_weight`."""
    ctx = {key: win[key][idx] for key in CTX + ["agent_route"] if key in win}
    target, seen, mask = win["target"][idx], win["seen"][idx], win["loss_mask"][idx]
    b, n, k = target.shape
    x = target + noise * sigma.reshape(b, 1, 1).float()
    enc = model.encode_map(ctx)
    d = model.denoise(ctx, enc, x, sigma)
    diff = d - target
    if model.sdk is None or not per_component_weight:
        sd = edm["sigma_data"]
        w = ((sigma * sigma + sd * sd) / (sigma * sd) ** 2).float().reshape(b, 1)
    else:
        # EDM's weight 1/c_out², per component: each coefficient's error divided by its c_out
        # before the basis takes it to metres (for one sigma_data, the same as the weight
        # in the other branch).
        diff = diff / model.precondition(sigma)[1].float().to(d.device).reshape(b, 1, k)
        w = torch.ones(b, 1, device=d.device)
    traj = (diff.reshape(b * n, k) @ basis).reshape(b, n, -1)
    err = (traj.square() * seen).sum(-1) / k
    return (err * w * mask).sum() / mask.sum().clamp(min=1.0)


def learning_rate(lr, frac):
    """src/train/trainer.rs, learning_rate, over the fraction of the run's time done."""
    if frac <= 0.02:
        return lr * max(frac, 1e-4) / 0.02
    t = min((frac - 0.02) / 0.98, 1.0)
    return 0.1 * lr + 0.9 * lr * 0.5 * (1.0 + math.cos(math.pi * t))


def write_checkpoint(out, meta, weights, history, steps, batch, lr, half_life, revision):
    os.makedirs(out, exist_ok=True)
    meta = json.loads(json.dumps(meta))
    cfg = meta["config"]
    cfg["steps"], cfg["batch"], cfg["lr"], cfg["ema_half_life"] = steps, batch, lr, half_life
    meta["steps_done"], meta["ema_updates"], meta["history"] = steps, steps, history
    meta["git_revision"] = revision
    tmp = os.path.join(out, ".model.safetensors.tmp")
    save_file({k: v.detach().float().cpu().contiguous() for k, v in weights.items()}, tmp)
    os.replace(tmp, os.path.join(out, "model.safetensors"))
    tmp = os.path.join(out, ".config.json.tmp")
    with open(tmp, "w") as f:
        json.dump(meta, f, indent=2)
    os.replace(tmp, os.path.join(out, "config.json"))


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("data", help="a `drivescript train --export` directory")
    ap.add_argument("out", help="checkpoint directory to write")
    ap.add_argument("--check", help="the checkpoint the export was made with (--resume)")
    ap.add_argument("--init", help="start from this checkpoint's weights (default: fresh)")
    ap.add_argument("--d", type=int, help="width of a fresh network (default: the export's)")
    ap.add_argument("--layers", type=int, help="layers of a fresh network")
    ap.add_argument("--batch", type=int, default=128)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--ema-half-life", type=float, default=500.0)
    ap.add_argument("--eval-every", type=float, default=30.0, help="seconds")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--p-mean", type=float, help="EDM's P_mean for the training noise levels "
                    "(default: the export's, as `drivescript train --p-mean`)")
    ap.add_argument("--p-std", type=float, help="EDM's P_std (default: the export's)")
    ap.add_argument("--per-component-weight", action="store_true",
                    help="with --sigma-data-components, weigh each component's error by its own "
                         "1/c_out² (EDM's unit-variance target) instead of the one sigma_data's")
    ap.add_argument("--sigma-data-components", action="store_true",
                    help="precondition each PCA component by its own spread in the training "
                         "windows (at least 0.05) instead of the one sigma_data; the checkpoint "
                         "then holds `sigma_data_components`, which only this port reads")
    ap.add_argument("--revision", default=None, help="git revision to record")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--validate", nargs="+", metavar="CHECKPOINT",
                    help="only print these checkpoints' validation losses (the fixed set of "
                         "noise levels and noise of --seed and --batch) and stop")
    a = ap.parse_args()
    dev = torch.device(a.device)
    torch.backends.cuda.matmul.allow_tf32 = True
    torch.backends.cudnn.allow_tf32 = True
    with open(os.path.join(a.data, "config.json")) as f:
        meta = json.load(f)
    edm = meta["config"]["edm"]
    if a.p_mean is not None:
        edm["p_mean"] = a.p_mean
    if a.p_std is not None:
        edm["p_std"] = a.p_std
    basis = load_file(os.path.join(a.data, "basis.safetensors"))["basis"].to(dev)
    k = basis.shape[0]
    train = load_windows(a.data, "train", dev)
    val = load_windows(a.data, "val", dev)
    nt = train["target"].shape[0]
    print(f"{nt} training and {0 if val is None else val['target'].shape[0]} validation windows "
          f"on {dev}", flush=True)

    if a.check:
        check = load_file(os.path.join(a.data, "check.safetensors"))
        ref = Denoiser(None, meta, {n: t.to(dev) for n, t in checkpoint_weights(a.check).items()})
        sigma = check["sigma"].to(dev)
        idx = torch.arange(sigma.shape[0], device=dev)
        with torch.no_grad():
            torch.backends.cuda.matmul.allow_tf32 = False
            got = loss(ref, edm, train, basis, idx, sigma, check["noise"].to(dev)).item()
            torch.backends.cuda.matmul.allow_tf32 = True
        want = check["loss"].item()
        print(f"loss check: drivescript {want:.6f}, this port {got:.6f}", flush=True)
        if not abs(got - want) <= 1e-3 * abs(want):
            sys.exit("the port's loss differs from drivescript's: not training")

    if a.sigma_data_components:
        rows = train["target"][train["loss_mask"] > 0]
        edm["sigma_data_components"] = rows.double().std(0).clamp(min=0.05).tolist()
        print("per-component sigma_data: "
              + " ".join(f"{v:.2f}" for v in edm["sigma_data_components"]), flush=True)

    model_cfg = dict(meta["config"]["model"])
    gen = torch.Generator().manual_seed(a.seed)
    if a.init:
        with open(os.path.join(a.init, "config.json")) as f:
            model_cfg = json.load(f)["config"]["model"]
        weights = checkpoint_weights(a.init)
    else:
        model_cfg["d"] = a.d or model_cfg["d"]
        model_cfg["layers"] = a.layers or model_cfg["layers"]
        weights = fresh(model_cfg, k, gen)
    meta["config"]["model"] = model_cfg
    want_shapes = shapes(model_cfg, k)
    if {n: list(t.shape) for n, t in weights.items()} != want_shapes:
        sys.exit("the weights' names or shapes are not those of the network described")
    params = {n: torch.nn.Parameter(t.float().to(dev)) for n, t in weights.items()}
    model = Denoiser(None, meta, params)
    ema = {n: p.detach().clone() for n, p in params.items()}
    averaged = Denoiser(None, meta, ema)
    opt = torch.optim.AdamW(params.values(), lr=a.lr, betas=(0.9, 0.999), eps=1e-8,
                            weight_decay=1e-4)
    torch.manual_seed(a.seed)

    # A fixed validation set: the same windows, noise levels and noise at every evaluation.
    vg = torch.Generator(device=dev).manual_seed(a.seed ^ 0xABCD)
    val_sets = []
    if val is not None:
        nv = val["target"].shape[0]
        n = val["target"].shape[1]
        for start in range(0, nv, a.batch):
            idx = torch.arange(start, min(start + a.batch, nv), device=dev)
            z = torch.randn(len(idx), generator=vg, device=dev, dtype=torch.float64)
            sig = torch.exp(edm["p_mean"] + edm["p_std"] * z)
            val_sets.append((idx, sig, torch.randn(len(idx), n, k, generator=vg, device=dev)))

    def validate(m):
        if not val_sets:
            return None
        total, count = 0.0, 0
        with torch.no_grad():
            for idx, sig, noise in val_sets:
                total += loss(m, edm, val, basis, idx, sig, noise,
                              a.per_component_weight).item() * len(idx)
                count += len(idx)
        return total / count

    if a.validate:
        for ck in a.validate:
            with open(os.path.join(ck, "config.json")) as f:
                ck_meta = json.load(f)
            ck_meta["config"]["edm"] = edm
            tensors = load_file(os.path.join(ck, "model.safetensors"))
            m = Denoiser(None, ck_meta, {n: t.to(dev) for n, t in tensors.items()})
            print(f"{ck}: validation loss {validate(m):.6f}", flush=True)
        return

    start_val = validate(model)
    print(f"validation loss of the starting weights: {start_val}", flush=True)
    beta = 0.5 ** (1.0 / max(a.ema_half_life, 1e-9))
    budget = a.minutes * 60.0
    t0 = time.time()
    last_eval = t0
    history, best = [], None
    run_loss, run_n, step = 0.0, 0, 0
    n_agents = train["target"].shape[1]
    while True:
        frac = (time.time() - t0) / budget
        if frac >= 1.0:
            break
        step += 1
        for g in opt.param_groups:
            g["lr"] = learning_rate(a.lr, frac)
        idx = torch.randint(0, nt, (a.batch,), device=dev)
        z = torch.randn(a.batch, device=dev, dtype=torch.float64)
        sigma = torch.exp(edm["p_mean"] + edm["p_std"] * z)
        noise = torch.randn(a.batch, n_agents, k, device=dev)
        l = loss(model, edm, train, basis, idx, sigma, noise, a.per_component_weight)
        opt.zero_grad(set_to_none=True)
        l.backward()
        opt.step()
        with torch.no_grad():
            b = min(beta, (1.0 + step - 1) / (10.0 + step - 1))
            for n_, p in params.items():
                ema[n_].mul_(b).add_(p.detach(), alpha=1.0 - b)
        # Summed on the device: reading each step's loss would wait for the GPU every step.
        run_loss = run_loss + l.detach()
        run_n += 1
        now = time.time()
        if now - last_eval >= a.eval_every:
            last_eval = now
            v = validate(averaged)
            tr = float(run_loss) / max(run_n, 1)
            if not math.isfinite(tr) or (v is not None and not math.isfinite(v)):
                sys.exit(f"training diverged at step {step} (train {tr}, val {v})")
            history.append([step, tr, v])
            run_loss, run_n = 0.0, 0
            vs = "-" if v is None else f"{v:.4f}"
            print(f"step {step:>7}  {now - t0:6.0f} s  train {tr:.4f}  val {vs}  "
                  f"lr {learning_rate(a.lr, frac):.2e}", flush=True)
            if v is not None and (best is None or v < best):
                best = v
                write_checkpoint(os.path.join(a.out, "best"), meta, ema, history, step,
                                 a.batch, a.lr, a.ema_half_life, a.revision)
    v = validate(averaged)
    history.append([step, float(run_loss) / max(run_n, 1), v])
    write_checkpoint(os.path.join(a.out, "last"), meta, ema, history, step, a.batch, a.lr,
                     a.ema_half_life, a.revision)
    print(f"done: {step} steps of {a.batch} windows in {time.time() - t0:.0f} s; validation "
          f"loss {start_val} at the start, {v} at the end, best {best}", flush=True)


if __name__ == "__main__":
    main()
