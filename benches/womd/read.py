"""Reads a WOMD TFRecord file with Python's protobuf and prints its parse rate.

The reference for `drivescript bench io --womd FILE`'s "protos only" row: the same file, the
same Scenario messages (scenario.proto here mirrors src/io/womd_proto.rs), parsed with
`Scenario.FromString`. The framing is read in Python without checking the CRCs (drivescript
checks both), which favours Python.

    python3 read.py FILE [--seconds 1]
"""

import argparse
import importlib
import os
import struct
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def scenario_class():
    """Compiles scenario.proto (grpcio-tools' protoc) into a temporary module."""
    out = tempfile.mkdtemp(prefix="drivescript-womd-")
    subprocess.run(
        [sys.executable, "-m", "grpc_tools.protoc", f"-I{HERE}", f"--python_out={out}",
         os.path.join(HERE, "scenario.proto")],
        check=True,
    )
    sys.path.insert(0, out)
    return importlib.import_module("scenario_pb2").Scenario


def records(data):
    """The payloads of a TFRecord byte string (length, length CRC, payload, payload CRC)."""
    out, at = [], 0
    while at < len(data):
        if at + 12 > len(data):
            raise ValueError(f"truncated record header at byte {at}")
        (n,) = struct.unpack_from("<Q", data, at)
        start = at + 12
        if start + n + 4 > len(data):
            raise ValueError(f"truncated record at byte {at}")
        out.append(memoryview(data)[start:start + n])
        at = start + n + 4
    return out


def to_arrays(sc):
    """What a Python WOMD loader does next: every track's states and every map feature's
    points as numpy arrays (the fields drivescript's scenes keep)."""
    tracks = []
    for t in sc.tracks:
        states = np.array(
            [[s.center_x, s.center_y, s.length, s.width, s.heading, s.velocity_x, s.velocity_y,
              s.valid] for s in t.states], dtype=np.float64)
        tracks.append((t.id, t.object_type, states))
    features = []
    for f in sc.map_features:
        kind = f.WhichOneof("feature_data")
        data = getattr(f, kind)
        if kind in ("lane", "road_line", "road_edge"):
            pts = data.polyline
        elif kind == "stop_sign":
            pts = [data.position]
        else:
            pts = data.polygon
        xy = np.array([[p.x, p.y] for p in pts], dtype=np.float64)
        links = (list(data.entry_lanes), list(data.exit_lanes),
                 [n.feature_id for n in data.left_neighbors],
                 [n.feature_id for n in data.right_neighbors]) if kind == "lane" else None
        features.append((f.id, kind, xy, links))
    return tracks, features


def parse_all(path, scenario, arrays):
    with open(path, "rb") as f:
        data = f.read()
    n = 0
    for rec in records(data):
        sc = scenario.FromString(rec)
        if arrays:
            to_arrays(sc)
        n += 1
    return n


def rate(path, scenario, seconds, arrays):
    """(scenarios per second, MB per second, repetitions, scenarios), after a warm-up pass."""
    size = os.path.getsize(path)
    n = parse_all(path, scenario, arrays)
    reps, start = 0, time.perf_counter()
    while reps == 0 or time.perf_counter() - start < seconds:
        parse_all(path, scenario, arrays)
        reps += 1
    t = time.perf_counter() - start
    return n * reps / t, size * reps / t / 1e6, reps, n


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("file")
    ap.add_argument("--seconds", type=float, default=1.0)
    a = ap.parse_args()
    from google.protobuf.internal import api_implementation
    scenario = scenario_class()
    for arrays, what in ((False, "protos only"), (True, "protos + arrays")):
        per_s, mb_s, reps, n = rate(a.file, scenario, a.seconds, arrays)
        print(f"python protobuf ({api_implementation.Type()}), {what}: {n} scenarios, {reps} reps, "
              f"{per_s:.1f} scenarios/s, {1000 / per_s:.2f} ms/scenario, {mb_s:.1f} MB/s")


if __name__ == "__main__":
    main()
