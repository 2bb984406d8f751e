"""Checks the PyTorch port against drivescript's own outputs, then times unguided sampling in
both, interleaved, on the same machine. See README.md beside this file."""

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time

import torch
from safetensors.torch import load_file

from denoiser import Denoiser

ROW = re.compile(r"^\| sampling, unguided \| ([0-9.]+) \|$", re.M)


def drivescript_run(binary, args, threads):
    env = dict(os.environ, RAYON_NUM_THREADS=str(threads))
    return subprocess.run([binary, "bench", "sample", *args], check=True, capture_output=True,
                          text=True, env=env).stdout


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    root = os.path.normpath(os.path.join(here, "..", ".."))
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--drivescript", default=os.path.join(root, "target/release/drivescript"))
    ap.add_argument("--checkpoint", default=os.path.join(root, "data/checkpoint"))
    ap.add_argument("--rounds", type=int, default=5, help="interleaved timing rounds")
    ap.add_argument("--threads", type=int, default=torch.get_num_threads())
    a = ap.parse_args()
    torch.set_num_threads(a.threads)
    common = ["--checkpoint", a.checkpoint]
    with tempfile.TemporaryDirectory() as tmp:
        ref_path = os.path.join(tmp, "ref.safetensors")
        drivescript_run(a.drivescript, common + ["--only", "unguided", "--repeat", "1",
                                                 "--export", ref_path], a.threads)
        ref = load_file(ref_path)
    ctx = {k: ref[k] for k in ["lane_points", "lane_mask", "lane_rel", "agent_hist",
                               "agent_mask", "agent_attr", "agent_lane_rel", "agent_rel",
                               "agent_route"] if k in ref}
    ctx["lane_conn"] = ref["lane_conn"].long()
    sigmas = ref["sigmas"].double().tolist()
    model = Denoiser(a.checkpoint)
    with torch.inference_mode():
        enc = model.encode_map(ctx)
        d0 = model.denoise(ctx, enc, ref["x0"], sigmas[0])
        final = model.sample(ctx, ref["x0"], sigmas)
    present = ref["agent_mask"].bool()
    for name, ours, theirs in [("first denoised estimate", d0, ref["d0"]),
                               ("final sample", final, ref["x_final"])]:
        dc = (ours - theirs)[present].abs().max().item()
        dm = (model.metres(ours) - model.metres(theirs))[present].norm(dim=-1).max().item()
        print(f"{name}: max |coefficient difference| {dc:.2e}, max position difference {dm:.2e} m")
    torch_times, ds_times = [], []
    with torch.inference_mode():
        model.sample(ctx, ref["x0"], sigmas)  # warm-up
        for _ in range(a.rounds):
            t = time.perf_counter()
            model.sample(ctx, ref["x0"], sigmas)
            torch_times.append(time.perf_counter() - t)
            out = drivescript_run(a.drivescript, common + ["--only", "unguided", "--repeat", "1"],
                                  a.threads)
            ds_times.append(float(ROW.search(out).group(1)))
    ratios = [d / t for d, t in zip(ds_times, torch_times)]
    print(f"unguided sampling, 32 Heun steps, {a.threads} threads, {a.rounds} interleaved rounds:")
    print(f"  drivescript {statistics.median(ds_times):.3f} s, PyTorch {torch.__version__} "
          f"{statistics.median(torch_times):.3f} s, drivescript/PyTorch median ratio "
          f"{statistics.median(ratios):.2f} (min {min(ratios):.2f}, max {max(ratios):.2f})")


if __name__ == "__main__":
    sys.exit(main())
