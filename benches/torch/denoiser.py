"""A PyTorch port of drivescript's denoiser (src/model/) that loads a drivescript checkpoint.

It exists to check drivescript against an independent implementation and to measure the speed
ratio on the same machine (see README.md beside this file). It mirrors the Rust code
operation for operation; nothing here is used by drivescript itself.
"""

import json
import math
import os

import torch
import torch.nn.functional as F
from safetensors.torch import load_file


class Weights:
    """The checkpoint's tensors by name (`prefix.name`)."""

    def __init__(self, tensors):
        self.t = tensors

    def linear(self, name, x, bias=True):
        y = x @ self.t[name + ".weight"].T
        if bias:
            y = y + self.t[name + ".bias"]
        return y

    def norm(self, name, x):
        # Gain-only norms (`ln_k`, `ln_r`) have no bias tensor.
        w, b = self.t[name + ".weight"], self.t.get(name + ".bias")
        return F.layer_norm(x, (x.shape[-1],), w, b, 1e-5)


def pairs(w, p, rel, scores, conn=None):
    """RelAttention::pairs: the key and value pair features, computed once per scene."""
    hk = w.linear(p + ".rk1", rel)
    hv = w.linear(p + ".rv1", rel)
    if conn is not None:
        # A one-hot product, not `table[conn]`: the backward pass of indexing with five
        # distinct kinds among a million entries took CUDA seconds per step.
        table = w.t[p + ".conn.weight"]
        e = F.one_hot(conn, table.shape[0]).to(table.dtype) @ table
        hk = hk + e
        hv = hv + e
    hk, hv = torch.relu(hk), torch.relu(hv)
    if scores == "normalised":
        hk = w.norm(p + ".ln_r", hk @ w.t[p + ".rk2.weight"].T)
    return hk, hv


def rel_attention(w, p, xq, xk, pair, mask, scores):
    """src/model/attention.rs, RelAttention::forward (the factored form).

    Checkpoints from before the softmax fix also hold `k.bias` and `rk2.bias`; both add the
    same amount to every score of a row, which the softmax ignores, so they are not read.
    """
    hq = w.norm(p + ".ln1", xq)
    if scores == "normalised":
        hk_in = w.norm(p + ".ln_kv", xk)
        q = w.norm(p + ".ln_q", w.linear(p + ".q", hq))
        k = w.norm(p + ".ln_k", w.linear(p + ".k", hk_in, bias=False))
        v = w.linear(p + ".v", hk_in)
    else:
        q = w.linear(p + ".q", hq)
        k = w.linear(p + ".k", xk, bias=False)
        v = w.linear(p + ".v", xk)
    hk, hv = pair
    b, n, m, d = hk.shape
    qw = q if scores == "normalised" else q @ w.t[p + ".rk2.weight"]
    qh = (hk.reshape(b * n, m, d) @ qw.reshape(b * n, d, 1)).reshape(b, n, m)
    s = (q @ k.transpose(1, 2) + qh) / math.sqrt(d)
    keep = mask.unsqueeze(1)
    a = torch.softmax(s + (keep - 1.0) * 1e9, dim=-1) * keep
    ah = (a.reshape(b * n, 1, m) @ hv.reshape(b * n, m, d)).reshape(b, n, d)
    out = a @ v + ah @ w.t[p + ".rv2.weight"].T + a.sum(-1, keepdim=True) * w.t[p + ".rv2.bias"]
    x = xq + w.linear(p + ".o", out)
    f = w.linear(p + ".ff2", torch.relu(w.linear(p + ".ff1", w.norm(p + ".ln2", x))))
    return x + f


class Denoiser:
    """src/model/denoiser.rs with EDM preconditioning (src/model/edm.rs)."""

    def __init__(self, checkpoint, meta=None, tensors=None):
        """From a checkpoint directory, or from its metadata (`config.json`'s contents) and
        weights by name (training: the tensors may be parameters)."""
        if meta is None:
            with open(os.path.join(checkpoint, "config.json")) as f:
                meta = json.load(f)
        if tensors is None:
            tensors = load_file(os.path.join(checkpoint, "model.safetensors"))
        self.meta = meta
        cfg = self.meta["config"]
        self.model = cfg["model"]
        self.edm = cfg["edm"]
        # A config without `scores` predates the normalised form (DenoiserConfig::scores).
        self.scores = self.model.get("scores", "raw")
        # Per-component data spreads (`sigma_data_components`, benches/torch/train.py's
        # --sigma-data-components): EDM's preconditioning assumes every coordinate spreads by
        # sigma_data, which the capped PCA scales break (the largest components spread by up
        # to 18 times it). Absent: the one sigma_data, as drivescript.
        sdk = self.edm.get("sigma_data_components")
        self.sdk = None if sdk is None else torch.tensor(sdk, dtype=torch.float64)
        self.w = Weights(tensors)

    def encode_map(self, ctx):
        """Denoiser::encode_scene: the lanes after lane-lane attention and every layer's
        agent-lane and agent-agent pair features."""
        w, sc = self.w, self.scores
        h = torch.relu(w.linear("lanes.l1", ctx["lane_points"]))
        h = torch.relu(w.linear("lanes.l2", h))
        x = w.linear("lanes.l3", h.max(dim=-2).values)
        for i in range(self.model["layers"]):
            p = f"lane_lane{i}"
            pair = pairs(w, p, ctx["lane_rel"], sc, ctx["lane_conn"])
            x = rel_attention(w, p, x, x, pair, ctx["lane_mask"], sc)
        layers = range(self.model["layers"])
        return {
            "lanes": x,
            "agent_lane": [pairs(w, f"agent_lane{i}", ctx["agent_lane_rel"], sc) for i in layers],
            "agent_agent": [pairs(w, f"agent_agent{i}", ctx["agent_rel"], sc) for i in layers],
        }

    def precondition(self, sigma):
        """c_skip, c_out, c_in and c_noise for one noise level or one per batch row (`[B]`),
        computed in float64 like src/model/edm.rs."""
        sigma = torch.as_tensor(sigma, dtype=torch.float64)
        c_noise = torch.log(sigma) / 4.0
        if self.sdk is None:
            sd, s = self.edm["sigma_data"], sigma
        else:
            # [K], or [B, K] for one level per row.
            sd, s = self.sdk, sigma[..., None]
        s2 = s * s
        root = torch.sqrt(s2 + sd * sd)
        return (sd * sd / (s2 + sd * sd), s * sd / root, 1.0 / root, c_noise)

    def denoise(self, ctx, enc, x, sigma):
        w = self.w
        b, n, _ = x.shape
        # One noise level for the batch, or one per row (training).
        c_skip, c_out, c_in, c_noise = (v.to(torch.float32).to(x.device)
                                        for v in self.precondition(sigma))
        if c_noise.dim() == 1:
            c_skip, c_out, c_in = (c.reshape(b, 1, -1) for c in (c_skip, c_out, c_in))
            c_noise = c_noise.reshape(b, 1)
        freqs = torch.tensor([2.0 ** i for i in range(self.model["noise_freqs"])],
                             device=x.device)
        z = c_noise[..., None] * freqs
        noise = torch.cat([z.sin(), z.cos()], dim=-1).expand(b, n, -1)
        # What each agent is (type, static, length, width) for models that take it
        # (`attrs` in the config; checkpoints without the field take none).
        attrs = self.model.get("attrs", 0)
        parts = [ctx["agent_hist"]]
        if attrs > 0:
            parts.append(ctx["agent_attr"][..., :attrs])
        parts += [x * c_in, noise]
        # Futures told against lane routes (`route_frame`): the route ahead is an input.
        if self.model.get("route_frame", False):
            parts.append(ctx["agent_route"])
        feats = torch.cat(parts, dim=2)
        a = w.linear("agents.l2", torch.relu(w.linear("agents.l1", feats)))
        sc = self.scores
        for i in range(self.model["layers"]):
            a = rel_attention(w, f"agent_lane{i}", a, enc["lanes"], enc["agent_lane"][i],
                              ctx["lane_mask"], sc)
            a = rel_attention(w, f"agent_agent{i}", a, a, enc["agent_agent"][i],
                              ctx["agent_mask"], sc)
        f = w.linear("head2", torch.relu(w.linear("head1", a)))
        return x * c_skip + f * c_out

    def sample(self, ctx, x0, sigmas):
        """EDM's Heun sampler, unguided (src/sample/guided.rs, `heun`)."""
        enc = self.encode_map(ctx)
        x = x0
        for i in range(len(sigmas) - 1):
            s0, s1 = sigmas[i], sigmas[i + 1]
            d0 = self.denoise(ctx, enc, x, s0)
            slope = (x - d0) / s0
            nxt = x + slope * (s1 - s0)
            if s1 > 0:
                d1 = self.denoise(ctx, enc, nxt, s1)
                nxt = x + (slope + (nxt - d1) / s1) * (0.5 * (s1 - s0))
            x = nxt
        return x

    def metres(self, coeffs):
        """Normalised coefficients `[..., K]` -> future residual positions `[..., T, 2]` in metres
        (src/train/batch.rs, Normaliser::decode): what a coefficient error means on the road."""
        norm = self.meta["normaliser"]
        pca = norm["pca"]
        comps = torch.tensor(pca["components"], dtype=torch.float64).reshape(-1, pca["dim"])
        scale = torch.tensor(norm["std"], dtype=torch.float64) / norm["sigma_data"]
        v = (coeffs.double() * scale) @ comps
        return v.reshape(*coeffs.shape[:-1], -1, 3)[..., :2]
