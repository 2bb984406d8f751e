"""Attention statistics of a drivescript checkpoint, per block, on the bench scene.

For each attention block of one denoiser evaluation: the mean norm of its query and key
inputs, the spread of its scores (standard deviation of the query-key and query-pair terms
over present keys), the attention's entropy relative to uniform (1 = uniform, 0 = one key
only) and the mean largest weight. It is how the collapse of trained raw scores was found
(docs/model.md): every agent-agent row had entropy near 0.

    python benches/torch/attention.py CHECKPOINT [CHECKPOINT ...] [--sigma 1.0]

The scene is the one `drivescript bench sample --export` writes (24 agents, 200 lanes); the
first checkpoint's bench run exports it.
"""

import argparse
import math
import os
import subprocess
import sys
import tempfile

import torch
from safetensors.torch import load_file

sys.path.insert(0, os.path.dirname(__file__))
import denoiser as D  # noqa: E402


def main():
    root = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("checkpoints", nargs="+")
    ap.add_argument("--drivescript", default=os.path.join(root, "target/release/drivescript"))
    ap.add_argument("--sigma", type=float, default=1.0, help="noise level of the evaluation")
    a = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "ref.safetensors")
        subprocess.run([a.drivescript, "bench", "sample", "--checkpoint", a.checkpoints[0],
                        "--only", "unguided", "--repeat", "1", "--export", path],
                       check=True, stdout=subprocess.DEVNULL)
        ref = load_file(path)
    ctx = {k: ref[k] for k in ["lane_points", "lane_mask", "lane_rel", "agent_hist",
                               "agent_mask", "agent_lane_rel", "agent_rel"]}
    ctx["lane_conn"] = ref["lane_conn"].long()
    rows = []
    plain = D.rel_attention

    def traced(w, p, xq, xk, pair, mask, scores):
        hq = w.norm(p + ".ln1", xq)
        if scores == "normalised":
            kin = w.norm(p + ".ln_kv", xk)
            q = w.norm(p + ".ln_q", w.linear(p + ".q", hq))
            k = w.norm(p + ".ln_k", w.linear(p + ".k", kin, bias=False))
            qw = q
        else:
            q = w.linear(p + ".q", hq)
            k = w.linear(p + ".k", xk, bias=False)
            qw = q @ w.t[p + ".rk2.weight"]
        hk = pair[0]
        b, n, m, d = hk.shape
        qh = (hk.reshape(b * n, m, d) @ qw.reshape(b * n, d, 1)).reshape(b, n, m)
        qk = q @ k.transpose(1, 2)
        keep = mask.unsqueeze(1).expand_as(qk).bool()
        s = (qk + qh) / math.sqrt(d) + (mask.unsqueeze(1) - 1.0) * 1e9
        att = torch.softmax(s, dim=-1)
        present = keep.sum(-1)
        live = present > 1
        ent = -(att.clamp(min=1e-12).log() * att).sum(-1)
        rel = ent[live] / present[live].float().log()
        rows.append((p, xq.norm(dim=-1).mean().item(), xk.norm(dim=-1).mean().item(),
                     (qk[keep] / math.sqrt(d)).std().item(), (qh[keep] / math.sqrt(d)).std().item(),
                     rel.mean().item(), att.max(-1).values[live].mean().item()))
        return plain(w, p, xq, xk, pair, mask, scores)

    D.rel_attention = traced
    for ck in a.checkpoints:
        model = D.Denoiser(ck)
        rows.clear()
        with torch.inference_mode():
            enc = model.encode_map(ctx)
            model.denoise(ctx, enc, ref["x0"] * a.sigma / ref["sigmas"][0].item(), a.sigma)
        print(f"{ck} (scores: {model.scores}, σ = {a.sigma})")
        print("  block          |x_q|   |x_k|  spread q·k  spread q·pair  entropy  max weight")
        for p, nq, nk, sk, sh, ent, mx in rows:
            print(f"  {p:13s} {nq:6.1f} {nk:7.1f} {sk:11.2f} {sh:14.2f} {ent:8.3f} {mx:11.3f}")


if __name__ == "__main__":
    main()
