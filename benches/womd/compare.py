"""drivescript's WOMD reading against Python's protobuf, interleaved, with ratios.

Each round times Python (protos only, then protos + numpy arrays) in this process and then
`drivescript bench io --womd FILE` (and `--before BIN`, an older build, when given) as a
subprocess; the table gives each figure's median over the rounds and the ratios of medians.

    python3 compare.py FILE [--drivescript BIN] [--before BIN] [--rounds 5] [--seconds 1]
"""

import argparse
import os
import re
import statistics
import subprocess

import read

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def drivescript_rates(binary, path, seconds):
    """MB/s of the two `bench io --womd` rows: into scenes, and protos only."""
    out = subprocess.run(
        [binary, "bench", "io", "--womd", path, "--seconds", str(seconds)],
        check=True, capture_output=True, text=True,
    ).stdout
    rates = {}
    for line in out.splitlines():
        m = re.match(r"\| WOMD → (scenes|protos only) .*\|\s*([\d.]+) \|$", line)
        if m:
            rates[m.group(1)] = float(m.group(2))
    if set(rates) != {"scenes", "protos only"}:
        raise SystemExit(f"{binary}: no WOMD rows in its output:\n{out}")
    return rates


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("file")
    ap.add_argument("--drivescript", default=os.path.join(ROOT, "target/release/drivescript"))
    ap.add_argument("--before", help="an older drivescript build to time in the same rounds")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--seconds", type=float, default=1.0)
    a = ap.parse_args()
    scenario = read.scenario_class()
    runs = {}

    def add(name, mb_s):
        runs.setdefault(name, []).append(mb_s)

    for _ in range(a.rounds):
        for arrays, what in ((False, "python protobuf, protos only"),
                             (True, "python protobuf, protos + arrays")):
            add(what, read.rate(a.file, scenario, a.seconds, arrays)[1])
        for label, binary in (("drivescript", a.drivescript), ("before", a.before)):
            if binary:
                for row, mb_s in drivescript_rates(binary, a.file, a.seconds).items():
                    add(f"{label}, {row}", mb_s)
    med = {k: statistics.median(v) for k, v in runs.items()}
    base = med["python protobuf, protos + arrays"]
    print(f"{os.path.getsize(a.file) / 1e6:.1f} MB, {a.rounds} interleaved rounds\n")
    print("| reader | MB/s (median) | min | max | × Python protos + arrays |")
    print("|---|---|---|---|---|")
    for k, v in runs.items():
        print(f"| {k} | {med[k]:.1f} | {min(v):.1f} | {max(v):.1f} | {med[k] / base:.2f} |")
    if a.before:
        for row in ("scenes", "protos only"):
            print(f"\ndrivescript / before, {row}: "
                  f"{med[f'drivescript, {row}'] / med[f'before, {row}']:.2f}")
    print(f"drivescript protos only / Python protos only: "
          f"{med['drivescript, protos only'] / med['python protobuf, protos only']:.2f}")


if __name__ == "__main__":
    main()
