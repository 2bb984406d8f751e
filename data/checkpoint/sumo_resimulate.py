#!/usr/bin/env python3
"""Simulates longer urban scenes with SUMO from CommonRoad "interactive" scenarios.

The urban corpora in ../shared/data hold 3.5 s scenes for most towns, too short for 8 s
futures (to train on) and with too few yield requests (to measure). The CommonRoad scenario
repository (the public mirror seungju-k1m/CommonRoad, scenarios/interactive/scenario-factory/)
has, for the same towns, each scene's SUMO network, routes and the CommonRoad map. This script runs SUMO
on each and writes a CommonRoad 2020a file with the scene's own map and the simulated
trajectories, which `convert` and `heldout_cities.sh` then cut into instances.

What comes out is SUMO-simulated traffic on OpenStreetMap maps, like the corpora: say so
beside every figure that rests on it. A SUMO release other than the one that made the
repository's files simulates the same starting states differently; the scenes are not a
replay of the original recordings.

Re-simulate only towns that the corpora hold: some towns are kept out of them on purpose, for
independent checks. `train` splits by town name, so a held-out town's re-simulation stays
held out as long as it is given only to measuring.

Needs only SUMO (`python3 -m pip install eclipse-sumo`, or a `sumo` binary on PATH, or
$SUMO_BINARY).

Usage: sumo_resimulate.py OUT_DIR SCENARIO_DIR... [--seconds 12] [--towns A,B]
  SCENARIO_DIR holds NAME.sumo.cfg, NAME.cr.xml and the files the .cfg names.
"""
import argparse
import gzip
import math
import os
import shutil
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET

# SUMO vehicle class -> CommonRoad obstacle type.
CR_TYPE = {
    "passenger": "car",
    "bicycle": "bicycle",
    "bus": "bus",
    "truck": "truck",
    "motorcycle": "motorcycle",
}


def sumo_binary():
    if os.environ.get("SUMO_BINARY"):
        return os.environ["SUMO_BINARY"]
    try:
        import sumo  # eclipse-sumo's wheel

        return os.path.join(os.path.dirname(sumo.__file__), "bin", "sumo")
    except ImportError:
        found = shutil.which("sumo")
        if found:
            return found
    sys.exit("sumo_resimulate.py: no SUMO: python3 -m pip install eclipse-sumo, or set SUMO_BINARY")


def vtypes(scenario_dir):
    """Each vType's length and width (SUMO reports the front bumper; CommonRoad the centre)."""
    out = {}
    for name in os.listdir(scenario_dir):
        if name.endswith((".add.xml", ".rou.xml")):
            path = os.path.join(scenario_dir, name)
            if os.path.getsize(path) < 20:
                continue
            for vt in ET.parse(path).getroot().iter("vType"):
                out[vt.get("id")] = (float(vt.get("length", 5.0)), float(vt.get("width", 1.8)))
    return out


def fit_max_speeds(run, name):
    """Raises a vType's maxSpeed to above every departSpeed of its vehicles in the copy.

    Some scenes start a cyclist faster than its type's maxSpeed, which SUMO refuses
    ("Departure speed ... is too high"); the recorded start state is what matters here.
    """
    routes = ET.parse(os.path.join(run, name + ".vehicles.rou.xml")).getroot()
    fastest = {}
    for v in routes.iter("vehicle"):
        speed = v.get("departSpeed")
        if speed and speed.replace(".", "", 1).isdigit():
            t = v.get("type")
            fastest[t] = max(fastest.get(t, 0.0), float(speed))
    for fname in os.listdir(run):
        if not fname.endswith((".add.xml", ".rou.xml")):
            continue
        path = os.path.join(run, fname)
        if os.path.getsize(path) < 20:
            continue
        tree = ET.parse(path)
        changed = False
        for vt in tree.getroot().iter("vType"):
            need = fastest.get(vt.get("id"), 0.0) / 0.7
            if need > float(vt.get("maxSpeed", 1e9)):
                vt.set("maxSpeed", f"{need:.3f}")
                changed = True
        if changed:
            tree.write(path)


def simulate(scenario_dir, name, seconds, work):
    """Runs SUMO in a copy of the scenario folder; returns the FCD file's path."""
    run = os.path.join(work, name)
    shutil.copytree(scenario_dir, run)
    fit_max_speeds(run, name)
    fcd = os.path.join(run, "fcd.xml")
    cmd = [
        sumo_binary(), "-c", os.path.join(run, name + ".sumo.cfg"), "--end", str(seconds + 0.1),
        "--fcd-output", fcd, "--fcd-output.acceleration", "true", "--precision", "4",
        "--no-step-log", "true", "--verbose", "false", "--seed", "0",
    ]
    done = subprocess.run(cmd, cwd=run, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{scenario_dir}: sumo exited {done.returncode}: {done.stderr[-500:]}")
    return fcd


def tracks(fcd, dims):
    """Per vehicle: type and the states by CommonRoad step (SUMO's first step is step 0)."""
    out = {}
    first = None
    for _, el in ET.iterparse(fcd, events=("end",)):
        if el.tag != "timestep":
            continue
        t = float(el.get("time"))
        vehicles = list(el.iter("vehicle"))
        if first is None and vehicles:
            first = t
        for v in vehicles:
            step = round((t - first) / 0.1)
            kind = v.get("type")
            length, width = dims.get(kind, (5.0, 1.8))
            heading = math.radians(90.0 - float(v.get("angle")))
            heading = math.atan2(math.sin(heading), math.cos(heading))
            x = float(v.get("x")) - 0.5 * length * math.cos(heading)
            y = float(v.get("y")) - 0.5 * length * math.sin(heading)
            track = out.setdefault(v.get("id"), {"type": kind, "states": {}})
            track["states"][step] = (x, y, heading, float(v.get("speed")), float(v.get("acceleration", 0.0)))
        el.clear()
    return out


def state_xml(parent, tag, step, s):
    st = ET.SubElement(parent, tag)
    pt = ET.SubElement(ET.SubElement(st, "position"), "point")
    ET.SubElement(pt, "x").text = f"{s[0]:.4f}"
    ET.SubElement(pt, "y").text = f"{s[1]:.4f}"
    ET.SubElement(ET.SubElement(st, "orientation"), "exact").text = f"{s[2]:.6f}"
    ET.SubElement(ET.SubElement(st, "time"), "exact").text = str(step)
    ET.SubElement(ET.SubElement(st, "velocity"), "exact").text = f"{s[3]:.4f}"
    ET.SubElement(ET.SubElement(st, "acceleration"), "exact").text = f"{s[4]:.4f}"


def write_scene(cr_file, out_file, found, dims):
    tree = ET.parse(cr_file)
    root = tree.getroot()
    shapes = {}
    for ob in list(root):
        if ob.tag == "dynamicObstacle":
            rect = ob.find("shape/rectangle")
            shapes[ob.get("id")] = (rect.find("length").text, rect.find("width").text)
        if ob.tag in ("dynamicObstacle", "planningProblem"):
            root.remove(ob)
    root.set("source", root.get("source", "") + "; re-simulated with SUMO by sumo_resimulate.py")
    n = 0
    cut = []
    for vid, track in sorted(found.items(), key=lambda kv: kv[0]):
        steps = sorted(track["states"])
        # A vehicle that leaves and comes back would need two tracks; keep its first run. So
        # for one that SUMO moves further in a step than its speed carries it (a teleport, or
        # a re-insertion under the same id): `convert` would refuse the jump, or it would read
        # as motion no car makes. The centre may move up to a length more than the speed says
        # where SUMO's heading turns at once in a junction (the centre is set back from the
        # front along it): that stays, as in the held-out scenes.
        length, width = shapes.get(vid) or tuple(f"{v}" for v in dims.get(track["type"], (5.0, 1.8)))
        run = [steps[0]]
        for s in steps[1:]:
            if s != run[-1] + 1:
                break
            a, b = track["states"][run[-1]], track["states"][s]
            if math.hypot(b[0] - a[0], b[1] - a[1]) > 0.1 * max(a[3], b[3]) + float(length) + 1.0:
                cut.append(f"{vid} cut at step {s} ({math.hypot(b[0] - a[0], b[1] - a[1]):.1f} m in 0.1 s)")
                break
            run.append(s)
        if len(run) < 2:
            continue
        ob = ET.SubElement(root, "dynamicObstacle", id=str(vid))
        ET.SubElement(ob, "type").text = CR_TYPE.get(track["type"], "car")
        rect = ET.SubElement(ET.SubElement(ob, "shape"), "rectangle")
        ET.SubElement(rect, "length").text = str(length)
        ET.SubElement(rect, "width").text = str(width)
        state_xml(ob, "initialState", run[0], track["states"][run[0]])
        traj = ET.SubElement(ob, "trajectory")
        for s in run[1:]:
            state_xml(traj, "state", s, track["states"][s])
        n += 1
    if n == 0:
        return n, cut
    tmp = out_file + ".part"
    with gzip.open(tmp, "wb") as f:
        tree.write(f, encoding="UTF-8", xml_declaration=True)
    os.replace(tmp, out_file)
    return n, cut


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out")
    ap.add_argument("scenarios", nargs="+")
    ap.add_argument("--seconds", type=float, default=12.0)
    ap.add_argument("--towns", default="", help="comma-separated town prefixes to keep (default: all)")
    a = ap.parse_args()
    towns = [t for t in a.towns.split(",") if t]
    os.makedirs(a.out, exist_ok=True)
    total = 0
    skipped = []
    with tempfile.TemporaryDirectory(prefix="sumo_resimulate.") as work:
        for d in a.scenarios:
            d = d.rstrip("/")
            name = os.path.basename(d)
            if towns and not any(name.startswith(t + "-") for t in towns):
                continue
            cfg = os.path.join(d, name + ".sumo.cfg")
            cr = os.path.join(d, name + ".cr.xml")
            if not os.path.isdir(d):
                skipped.append(f"{name}: {d} is not a directory")
                continue
            missing = [os.path.basename(f) for f in (cfg, cr) if not os.path.isfile(f)]
            if missing:
                # The public mirror has scenario folders with only the network (two of 863).
                skipped.append(f"{name}: {d} has no {' or '.join(missing)}")
                continue
            dims = vtypes(d)
            try:
                fcd = simulate(d, name, a.seconds, work)
            except RuntimeError as e:
                # A scene SUMO cannot start as written (a route with no connection) is left
                # out whole: dropping the vehicle would change everyone else's traffic.
                skipped.append(f"{name}: {e}")
                continue
            found = tracks(fcd, dims)
            n, cut = write_scene(cr, os.path.join(a.out, name + ".xml.gz"), found, dims)
            if n == 0:
                # `convert` refuses a scene without agents: nothing to learn or measure.
                skipped.append(f"{name}: no vehicle drove in the simulated {a.seconds:g} s")
                continue
            total += 1
            print(f"{name}: {n} agents" + "".join(f"; {c}" for c in cut))
    print(f"{total} scenes written to {a.out}; {len(skipped)} left out:")
    for line in skipped:
        print("  " + line.replace("\n", " "))


if __name__ == "__main__":
    main()
