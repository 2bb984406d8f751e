"""Writes synthetic_junction.json: a made-up scenario in GPUDrive's JSON format.

Nothing here comes from the Waymo Open Motion Dataset: the junction, the lanes and the four
road users are invented, in the layout GPUDrive's data_utils/process_waymo_files.py writes
(91 steps at 10 Hz, invalid states as -10000, radians, map_element_id in WOMD's numbering).

    python3 tests/data/gpudrive/make_synthetic.py
"""
import json
import math
import os

STEPS = 91
DT = 0.1
ERR = -10000.0


def arc(cx, cy, r, a0, a1, n=12):
    """Points on a circle about (cx, cy) from angle a0 to a1 (degrees)."""
    out = []
    for k in range(n + 1):
        a = math.radians(a0 + (a1 - a0) * k / n)
        out.append((cx + r * math.cos(a), cy + r * math.sin(a)))
    return out


def line(x0, y0, x1, y1, step=0.5):
    n = max(1, round(math.hypot(x1 - x0, y1 - y0) / step))
    return [(x0 + (x1 - x0) * k / n, y0 + (y1 - y0) * k / n) for k in range(n + 1)]


def geometry(points):
    return [{"x": round(x, 6), "y": round(y, 6), "z": 0.0} for x, y in points]


# Right-hand traffic; the junction at the origin; lanes 3.5 m wide, their centres 1.75 m from
# the road's centre line.
lanes = {
    1: line(-50, -1.75, -10, -1.75),  # eastbound approach
    2: line(-10, -1.75, 10, -1.75),  # eastbound straight on
    3: line(10, -1.75, 50, -1.75),  # eastbound exit
    4: arc(-10, -10, 8.25, 90, 0),  # eastbound right turn, to southbound
    5: line(-1.75, -10, -1.75, -50),  # southbound exit
    6: arc(-10, 10, 11.75, -90, 0),  # eastbound left turn, to northbound
    7: line(1.75, 10, 1.75, 50),  # northbound exit
    8: line(50, 1.75, 10, 1.75),  # westbound approach
    9: line(10, 1.75, -10, 1.75),  # westbound straight on
    10: line(-10, 1.75, -50, 1.75),  # westbound exit
    11: arc(10, 10, 8.25, -90, -180),  # westbound right turn, to northbound
}
roads = []
for lid, pts in lanes.items():
    roads.append({"geometry": geometry(pts), "type": "lane", "map_element_id": 2, "id": lid})
# Kerbs, road on their left (WOMD's orientation).
edges = [
    [(-50, -3.5), (-3.5, -3.5), (-3.5, -50)],
    [(3.5, -50), (3.5, -3.5), (50, -3.5)],
    [(50, 3.5), (3.5, 3.5), (3.5, 50)],
    [(-3.5, 50), (-3.5, 3.5), (-50, 3.5)],
]
for k, e in enumerate(edges):
    roads.append({"geometry": geometry(e), "type": "road_edge", "map_element_id": 15, "id": 20 + k})
# The centre line, solid double yellow, west and east arms.
roads.append({"geometry": geometry([(-50, 0), (-3.5, 0)]), "type": "road_line", "map_element_id": 12, "id": 30})
roads.append({"geometry": geometry([(3.5, 0), (50, 0)]), "type": "road_line", "map_element_id": 12, "id": 31})
roads.append({"geometry": geometry([(-8, -3.5), (-5, -3.5), (-5, 3.5), (-8, 3.5)]), "type": "crosswalk", "map_element_id": 18, "id": 40})
roads.append({"geometry": geometry([(-9, -4.5)]), "type": "stop_sign", "map_element_id": 17, "id": 41})
roads.append({"geometry": geometry([(30, -3.5), (30.6, -3.5), (30.6, 0), (30, 0)]), "type": "speed_bump", "map_element_id": 19, "id": 42})
roads.append({"geometry": geometry([(20, -3.5), (24, -3.5), (24, -8), (20, -8)]), "type": "driveway", "map_element_id": 20, "id": 43})


def track(oid, kind, size, pose, first=0):
    """pose(t) -> (x, y, heading, vx, vy); states before `first` are invalid."""
    obj = {"position": [], "width": size[1], "length": size[0], "height": 1.5, "heading": [],
           "velocity": [], "valid": []}
    for t in range(STEPS):
        if t < first:
            obj["position"].append({"x": ERR, "y": ERR, "z": ERR})
            obj["heading"].append(ERR)
            obj["velocity"].append({"x": ERR, "y": ERR})
            obj["valid"].append(False)
            continue
        x, y, h, vx, vy = pose(t)
        obj["position"].append({"x": round(x, 6), "y": round(y, 6), "z": 0.0})
        obj["heading"].append(h)
        obj["velocity"].append({"x": vx, "y": vy})
        obj["valid"].append(True)
    last = obj["position"][-1]
    obj["goalPosition"] = dict(last)
    obj["type"] = kind
    obj["id"] = oid
    obj["mark_as_expert"] = False
    return obj


objects = [
    # The self-driving car: eastbound at 8 m/s, straight through the junction.
    track(101, "vehicle", (4.5, 2.0), lambda t: (-45 + 8 * DT * t, -1.75, 0.0, 8.0, 0.0)),
    # A cyclist westbound at 4 m/s.
    track(202, "cyclist", (1.8, 0.7), lambda t: (40 - 4 * DT * t, 1.75, math.pi, -4.0, 0.0)),
    # A pedestrian on the crosswalk, northward at 1.3 m/s, first seen at step 5.
    track(303, "pedestrian", (0.6, 0.6), lambda t: (-6.5, -5 + 1.3 * DT * (t - 5), math.pi / 2, 0.0, 1.3), first=5),
    # A car parked by the eastbound exit's kerb.
    track(404, "vehicle", (4.6, 1.9), lambda t: (40.0, -2.6, 0.0, 0.0, 0.0)),
]
objects[3]["mark_as_expert"] = True

scenario = {
    "name": "synthetic_junction.json",
    "scenario_id": "synthetic_junction",
    "objects": objects,
    "roads": roads,
    # GPUDrive skips scenarios with signals; Nocturne keeps them, keyed by lane.
    "tl_states": {"1": {"state": ["go", "go", "caution"], "x": [-10.0] * 3, "y": [-1.75] * 3,
                        "z": [0.0] * 3, "time_index": [8, 9, 10]}},
    "metadata": {"sdc_track_index": 0, "objects_of_interest": [101, 202],
                 "tracks_to_predict": [{"track_index": 1, "difficulty": 0}]},
}
here = os.path.dirname(os.path.abspath(__file__))
with open(os.path.join(here, "synthetic_junction.json"), "w") as f:
    json.dump(scenario, f)
