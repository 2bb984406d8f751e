"""Every line of the package's contract (python/README.md), and the CLI's numbers."""

import re
import json
import subprocess
import threading
import time

import numpy as np
import pytest

from conftest import CUT_IN, CUT_IN_PARAMS, ROOT, SCENE


def test_scene_exposes_ids_dt_and_current_step(scene):
    assert isinstance(scene.agent_ids, list) and all(isinstance(i, int) for i in scene.agent_ids)
    assert 401 in scene.agent_ids and 405 in scene.agent_ids
    assert isinstance(scene.dt, float) and scene.dt == pytest.approx(0.1)
    assert isinstance(scene.current_step, int) and scene.current_step == 10
    assert "USA_US101-4_1_T-1" in repr(scene)


def test_log_future_is_float64_agents_by_steps_by_3_with_nan_where_unobserved(scene):
    traj = scene.log_future(40)
    assert traj.dtype == np.float64
    assert traj.shape == (len(scene.agent_ids), 40, 3)
    nan = np.isnan(traj)
    # A state is observed or not as a whole.
    assert (nan.all(axis=2) == nan.any(axis=2)).all()
    assert nan.any() and not nan.all()
    longer = scene.log_future(scene.future_steps + 5)
    assert np.isnan(longer[:, -5:, :]).all(), "past the recording is unobserved"
    assert scene.log_future().shape[1] == scene.future_steps


def test_filled_future_fills_the_gaps_of_the_recording_at_constant_velocity(scene):
    log, filled = scene.log_future(60), scene.filled_future(60)
    assert filled.shape == log.shape and not np.isnan(filled).any()
    seen = ~np.isnan(log)
    assert (filled[seen] == log[seen]).all()
    # An agent that leaves keeps its last observed heading and moves on in a straight line.
    a, k = np.argwhere(np.isnan(log[:, :, 0]) & ~np.isnan(log[:, :1, 0]))[0]
    e = k + np.argmax(np.append(~np.isnan(log[a, k:, 0]), True))  # the gap is k..e
    assert np.ptp(filled[a, k - 1 : e, 2]) == 0
    step = np.diff(filled[a, k - 1 : e, :2], axis=0)
    assert len(step) > 1 and np.allclose(step, step[0])


def test_a_crop_is_the_bench_scene(ds, scene):
    c = scene.crop(8, 30)
    assert len(c.agent_ids) == 8 and c.future_steps == 30
    assert set(c.agent_ids) <= set(scene.agent_ids)
    assert not np.isnan(c.log_history()[:, -1]).any(), "every agent is observed now"
    with pytest.raises(ValueError, match="steps, .* are needed"):
        scene.crop(8, 10_000)


def test_sizes_types_and_lane_paths_are_the_ones_scripts_see(ds, scene):
    # What a port of a script to another framework needs besides the trajectories: each
    # agent's footprint and type, and the centre lines Frenet coordinates are measured on.
    sizes, types = scene.agent_sizes, scene.agent_types
    assert sizes.dtype == np.float64 and sizes.shape == (len(scene.agent_ids), 2)
    assert len(types) == len(scene.agent_ids) and set(types) <= {"vehicle", "pedestrian", "cyclist", "other"}
    k = scene.agent_ids.index(405)
    probe = ds.CostScript.from_source(
        "let b = agent(405);\n"
        "let p = b.lane_path();\n"
        "let q = lane_path(b.lane, 120.0);\n"
        "let r = b.lane_path(20.0, \"left\");\n"
        "print(`${b.length} ${b.width} ${b.type} ${b.lane} ${p.length} ${q.length} ${r.length}`);\n"
        "term(\"d\", b.frenet(p).d.last() * b.frenet(q).d.last());\n"
    )
    length, width, kind, lane, p_len, q_len, r_len = probe.evaluate(scene, scene.log_future(40)).prints[0].split()
    assert (sizes[k, 0], sizes[k, 1], types[k]) == (float(length), float(width), kind)
    paths = [
        (scene.agent_lane_path(405), p_len),
        (scene.lane_path(int(lane), 120.0), q_len),
        (scene.agent_lane_path(405, 20.0, "left"), r_len),
    ]
    for line, want in paths:
        assert line.dtype == np.float64 and line.ndim == 2 and line.shape[1] == 2
        assert np.linalg.norm(np.diff(line, axis=0), axis=1).sum() == pytest.approx(float(want), rel=1e-12)
    for call, says in [
        (lambda: scene.agent_lane_path(999999), "no agent 999999"),
        (lambda: scene.agent_lane_path(405, turn="sideways"), "turn"),
        (lambda: scene.lane_path(int(lane), -1.0), "length"),
        # Printed with all 301 digits.
        (lambda: scene.agent_lane_path(405, 1e300), r"^length 1e300: must be in"),
        (lambda: scene.lane_path(-12345, 100.0), "lane -12345"),
    ]:
        with pytest.raises(ValueError, match=says):
            call()


def test_every_format_the_cli_reads_loads(ds):
    for p in [
        "data/samples/commonroad/USA_Peach-4_8_T-1.xml",
        "data/samples/yaml/highway_cut_in.yaml",
        "data/samples/av2",
    ]:
        s = ds.Scene.load(ROOT / p)
        assert len(s.agent_ids) > 0 and s.future_steps > 0, p


def test_evaluate_gives_total_terms_and_a_gradient_shaped_like_the_trajectories(scene, cut_in):
    traj = scene.log_future(40)
    r = cut_in.evaluate(scene, traj)
    assert isinstance(r.total, float) and np.isfinite(r.total)
    assert isinstance(r.terms, dict) and r.terms and all(isinstance(v, float) for v in r.terms.values())
    assert r.total == pytest.approx(sum(r.weights[k] * v for k, v in r.terms.items()), rel=1e-12)
    assert isinstance(r.grad, np.ndarray) and r.grad.shape == traj.shape and r.grad.dtype == np.float64
    assert np.abs(r.grad).sum() > 0
    assert (r.grad[np.isnan(traj)] == 0).all(), "unobserved states have no gradient"
    assert cut_in.name == str(CUT_IN) and cut_in.params == CUT_IN_PARAMS


def test_evaluate_batch_equals_evaluate_item_by_item(scene, cut_in):
    traj = scene.log_future(40)
    rng = np.random.default_rng(0)
    batch = np.stack([traj] * 64)
    batch[:, :, :, :2] += rng.normal(0, 0.3, size=batch[:, :, :, :2].shape)
    rs = cut_in.evaluate_batch(scene, batch)
    assert len(rs) == 64
    for b in (0, 17, 63):
        one = cut_in.evaluate(scene, batch[b])
        assert rs[b].total == one.total
        assert np.array_equal(rs[b].grad, one.grad)
    assert len({r.total for r in rs}) > 1


def test_ctrl_c_stops_a_long_evaluate_batch_and_leaves_the_script_usable(ds, scene):
    # About 50 ms an item: 400 items took 10 s on two cores, and a Ctrl-C waited for them all.
    slow = ds.CostScript.from_source(
        'let x = agent(401).x;\nlet s = 0.0;\nfor i in 0..200000 { s += 1.0; }\n'
        'term("t", x.mean() + s * 0.0);\n',
        name="slow.rhai",
    )
    traj = np.nan_to_num(scene.log_future(40))
    batch = np.stack([traj] * 400)
    interrupted_within(3.0, lambda: slow.evaluate_batch(scene, batch))
    assert len(slow.evaluate_batch(scene, batch[:2])) == 2


def interrupted_within(seconds, call):
    """Sends this process SIGINT 0.5 s into `call` and checks that `call` raises
    KeyboardInterrupt within `seconds` of its start."""
    import os
    import signal

    # A process started in the background by a non-interactive shell (`cmd &`, as CI may run
    # the suite) inherits SIGINT ignored, and Python then installs no KeyboardInterrupt
    # handler: the signal would be dropped before drivescript could see it.
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        timer = threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT))
        t = time.perf_counter()
        timer.start()
        with pytest.raises(KeyboardInterrupt):
            call()
        assert time.perf_counter() - t < seconds, time.perf_counter() - t
        timer.join()
    finally:
        signal.signal(signal.SIGINT, before)


def test_evaluate_batch_releases_the_gil(scene, cut_in):
    # One call, long enough to tell on a fast machine as on a slow one: about half a second
    # by a timing of 64 rows. On a busy machine that timing can run slow and the batch then
    # come out too short, so a batch that was too quick is timed and sized again (one call
    # each: a loop of calls would let this thread run between them whatever the GIL does).
    traj = scene.log_future(40)
    for _ in range(3):
        per_64 = min(timed(lambda: cut_in.evaluate_batch(scene, np.stack([traj] * 64)))
                     for _ in range(3))
        batch = np.stack([traj] * min(8192, 64 * int(np.ceil(0.5 / per_64))))
        done = threading.Event()

        def run():
            cut_in.evaluate_batch(scene, batch)
            done.set()

        t = threading.Thread(target=run)
        ticks = 0
        t.start()
        start = time.perf_counter()
        while not done.is_set():
            ticks += 1
        elapsed = time.perf_counter() - start
        t.join()
        if elapsed > 0.05:
            break
    # With the GIL held for the whole batch this loop would not run until it ends.
    assert elapsed > 0.05, f"the batch was too quick to tell: {len(batch)} rows in {elapsed:.3f} s"
    assert ticks > 10_000, f"{ticks} iterations in {elapsed:.3f} s while the batch ran"


def timed(call):
    t = time.perf_counter()
    call()
    return time.perf_counter() - t


def write_rollout(scene, traj, path):
    scene.write_rollout(path, traj)
    return path


def cli_cost(cli, rollout=None, horizon=None):
    cmd = [cli, "cost", str(SCENE), "--script", str(CUT_IN), "--json", "--param"]
    cmd += [f"{k}={v}" for k, v in CUT_IN_PARAMS.items()]
    if rollout is not None:
        cmd += ["--rollout", str(rollout)]
    if horizon is not None:
        cmd += ["--horizon", str(horizon)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def assert_matches_cli(r, scene, want):
    assert abs(r.total - want["total"]) <= 1e-9
    terms = {t["name"]: t for t in want["terms"]}
    assert set(terms) == set(r.terms)
    for k, v in r.terms.items():
        assert abs(v - terms[k]["value"]) <= 1e-9, k
    norms = np.sqrt((r.grad.reshape(r.grad.shape[0], -1) ** 2).sum(axis=1))
    got = {a: n for a, n in zip(scene.agent_ids, norms) if n > 0}
    cli_norms = {g["agent"]: g["grad_norm"] for g in want["agent_grad_norms"]}
    assert set(got) == set(cli_norms)
    for a, n in got.items():
        assert abs(n - cli_norms[a]) <= 1e-9, a


def test_values_and_gradients_equal_the_cli_on_the_recording(scene, cut_in, cli):
    r = cut_in.evaluate(scene, scene.log_future(40))
    assert_matches_cli(r, scene, cli_cost(cli, horizon=40))


def test_values_and_gradients_equal_the_cli_on_perturbed_trajectories(scene, cut_in, cli, tmp_path):
    rng = np.random.default_rng(1)
    traj = scene.log_future(40)
    traj[:, :, :2] += rng.normal(0, 0.5, size=traj[:, :, :2].shape)
    r = cut_in.evaluate(scene, traj)
    path = write_rollout(scene, traj, tmp_path / "perturbed.json")
    assert_matches_cli(r, scene, cli_cost(cli, rollout=path))


def test_gradients_match_central_finite_differences(scene, cut_in):
    traj = scene.log_future(40)
    r = cut_in.evaluate(scene, traj)
    flat = np.argsort(-np.abs(r.grad).ravel())[:12]
    h = 1e-6
    for i in flat:
        idx = np.unravel_index(i, traj.shape)
        up, down = traj.copy(), traj.copy()
        up[idx] += h
        down[idx] -= h
        fd = (cut_in.evaluate(scene, up).total - cut_in.evaluate(scene, down).total) / (2 * h)
        assert fd == pytest.approx(r.grad[idx], rel=1e-5, abs=1e-6), idx


def test_a_wrong_shape_is_a_value_error_naming_the_shape(scene, cut_in):
    n = len(scene.agent_ids)
    for bad in [np.zeros((n - 1, 40, 3)), np.zeros((n, 40, 2)), np.zeros((n, 40)), np.zeros((n, 0, 3))]:
        with pytest.raises(ValueError, match=rf"expected shape \({n}, steps, 3\)"):
            cut_in.evaluate(scene, bad)
    with pytest.raises(ValueError, match=rf"expected shape \(batch, {n}, steps, 3\)"):
        cut_in.evaluate_batch(scene, np.zeros((n, 40, 3)))


def test_nested_lists_of_uneven_lengths_are_a_value_error_naming_the_shape(ds, scene, cut_in, tmp_path):
    # numpy's "setting an array element with a sequence" named neither the argument nor the
    # shape wanted.
    rag = scene.log_future(40).tolist()
    rag[0] = rag[0][:5]
    for call, arg in [
        (lambda: cut_in.evaluate(scene, rag), "traj"),
        (lambda: cut_in.evaluate_batch(scene, [rag]), "trajs"),
        (lambda: ds.check("cut_in", scene, rag, CUT_IN_PARAMS), "traj"),
        (lambda: scene.write_rollout(tmp_path / "r.json", rag), "traj"),
    ]:
        with pytest.raises(ValueError, match=rf"^{arg}: not an array of one shape \(.*\): expected shape \(.*22, steps, 3\)"):
            call()
    assert not (tmp_path / "r.json").exists()


def test_a_half_observed_state_is_a_value_error_naming_agent_and_step(scene, cut_in):
    traj = scene.log_future(40)
    a = int(np.argwhere(~np.isnan(traj[:, 3, 0]))[0][0])
    traj[a, 3, 1] = np.nan
    with pytest.raises(ValueError, match=f"agent index {a}, step 3: y is NaN"):
        cut_in.evaluate(scene, traj)


def test_other_dtypes_are_converted(scene, cut_in):
    traj = scene.log_future(40)
    a = cut_in.evaluate(scene, traj).total
    assert cut_in.evaluate(scene, traj.astype(np.float32)).total == pytest.approx(a, rel=1e-5)
    assert cut_in.evaluate(scene, traj.tolist()).total == a
    # Read in logical order whatever the memory order: Fortran order, a strided view.
    fortran = np.asfortranarray(traj)
    assert not fortran.flags.c_contiguous
    assert cut_in.evaluate(scene, fortran).total == a
    strided = np.concatenate([traj, traj], axis=2)[:, :, :3]
    assert not strided.flags.c_contiguous
    assert cut_in.evaluate(scene, strided).total == a


def test_complex_boolean_and_string_arrays_are_type_errors_not_converted(ds, scene, cut_in):
    # numpy's float64 conversion takes them all: complex with only a warning, dropping the
    # imaginary part; booleans as 0 and 1; numeric strings parsed.
    traj = scene.log_future(40)
    for bad, what in [
        (traj + 1j, "complex numbers"),
        (np.isnan(traj), "booleans"),
        (traj.astype(str), "strings"),
    ]:
        with pytest.raises(TypeError, match=f"traj: an array of .*{what}"):
            cut_in.evaluate(scene, bad)
        with pytest.raises(TypeError, match=f"trajs: an array of .*{what}"):
            cut_in.evaluate_batch(scene, bad[None])
        with pytest.raises(TypeError, match=what):
            ds.check("cut_in", scene, bad, {"cutter": 401, "victim": 405})


def test_an_object_array_holding_what_is_not_a_number_is_a_type_error(ds, scene, cut_in):
    # An object array (a list mixing types) converted element by element with float(): the
    # strings "1.0" and b"1.0" and True were taken for positions, None for NaN, where the
    # same values as an array of strings or booleans are refused.
    traj = scene.log_future(40)
    for bad, what in [("1.0", "str"), (b"1.0", "bytes"), (True, "bool"), (None, "NoneType")]:
        o = traj.astype(object)
        o[1, 0, 0] = bad
        with pytest.raises(TypeError, match=rf"traj: the element at \[1, 0, 0\] is .* of type {what}"):
            cut_in.evaluate(scene, o)
        with pytest.raises(TypeError, match=rf"trajs: the element at \[0, 1, 0, 0\] is .* of type {what}"):
            cut_in.evaluate_batch(scene, o[None])
    # An int past float64's range failed in numpy's conversion naming no element.
    o = traj.astype(object)
    o[1, 0, 2] = 10**400
    with pytest.raises(OverflowError, match=r"traj: the element at \[1, 0, 2\] is 1000.*\(401 characters\), which no float64 holds"):
        cut_in.evaluate(scene, o)
    # Numbers of any kind still convert.
    import fractions
    o = traj.astype(object)
    o[1, 0, 0] = fractions.Fraction(o[1, 0, 0]) if not np.isnan(traj[1, 0, 0]) else np.nan
    o[1, 0, 1] = np.float32(o[1, 0, 1])
    assert cut_in.evaluate(scene, o).total == pytest.approx(cut_in.evaluate(scene, traj).total)


def test_a_masked_array_is_refused_not_read_under_its_mask(ds, scene, cut_in, tmp_path):
    # numpy.asarray drops the mask: the values under it were read as positions.
    traj = scene.log_future(40)
    hidden = traj.copy()
    hidden[1, 5, :] = 1e6
    m = np.ma.masked_array(hidden, mask=np.zeros_like(hidden, dtype=bool))
    m[1, 5, :] = np.ma.masked
    for call in [
        lambda: cut_in.evaluate(scene, m),
        lambda: cut_in.evaluate_batch(scene, m[None]),
        lambda: ds.check("cut_in", scene, m, CUT_IN_PARAMS),
        lambda: scene.write_rollout(tmp_path / "m.json", m),
    ]:
        with pytest.raises(ValueError, match="a masked array with 3 masked values"):
            call()
    assert not (tmp_path / "m.json").exists()
    # One with nothing masked is its data.
    clear = np.ma.masked_array(traj, mask=False)
    assert cut_in.evaluate(scene, clear).total == cut_in.evaluate(scene, traj).total


def test_script_errors_carry_file_line_and_column(ds, scene):
    with pytest.raises(ds.ScriptError) as e:
        ds.CostScript.from_source("let x = ;\n", name="broken.rhai")
    assert e.value.file == "broken.rhai" and e.value.line == 1 and e.value.column is not None
    assert str(e.value).startswith("broken.rhai:1:") and "syntax error" in str(e.value)
    s = ds.CostScript.from_source('let a = agent(999999);\nterm("x", a.speed_at(0));\n', name="ghost.rhai")
    with pytest.raises(ds.ScriptError) as e:
        s.evaluate(scene, scene.log_future(40))
    assert e.value.file == "ghost.rhai" and e.value.line == 1


def test_limits_and_sandbox_are_the_cli_s(ds, scene):
    loop = ds.CostScript.from_source("let i = 0;\nloop { i += 1; }\n", name="loop.rhai")
    with pytest.raises(ds.ScriptError, match="limit exceeded: operations"):
        loop.evaluate(scene, scene.log_future(10))
    for src in ['eval("1")', 'import "std:fs" as fs;', 'open_file("/etc/passwd")']:
        with pytest.raises(ds.ScriptError):
            ds.CostScript.from_source(src + '\nterm("x", 1.0);\n', name="sandbox.rhai").evaluate(
                scene, scene.log_future(10)
            )
    assert ds.limits()["max_operations"] == 2_000_000


def test_arrays_nested_deep_do_not_overflow_a_thread_s_stack(ds):
    # Rhai compares, prints and size-checks nested arrays recursively: evaluate() on Python's
    # own thread overflowed its 8 MB comparing arrays 6,000 deep (a second of `a = [a]`), and
    # evaluate_batch() on rayon's 2 MB threads at 10,000 levels: the interpreter aborted
    # ("stack overflow"). Run apart, so that an abort fails this test alone.
    code = (
        "import sys, drivescript as ds\n"
        "scene = ds.Scene.load(sys.argv[1])\n"
        "def script(n, op):\n"
        "    return ds.CostScript.from_source('let a = [];\\nfor i in 0..' + str(n) + "
        "' { a = [a]; }\\n' + op + '\\nterm(\"t\", agent(401).x.mean());\\n', name='deep.rhai')\n"
        "for call in [lambda: script(6000, 'let b = a == a;').evaluate(scene, scene.log_future(10)),\n"
        "             lambda: script(12000, '').evaluate_batch(scene, scene.log_future(10)[None])]:\n"
        "    try:\n"
        "        call()\n"
        "        print('evaluated')\n"
        "    except ds.ScriptError as e:\n"
        "        print(e)\n"
    )
    import os
    import sys
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    out = subprocess.run(
        [sys.executable, "-c", code, str(SCENE)], capture_output=True, text=True, env=env, timeout=300
    )
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.split("\n")[:2]
    assert all(l == "evaluated" or "limit exceeded: wall time" in l for l in lines), out.stdout


def test_a_process_forked_after_use_evaluates_and_samples(ds):
    # multiprocessing's default on Linux (and a DataLoader's workers) forks: the child held
    # the pools' memory but none of their threads, and its first evaluate() or sample()
    # waited for them forever. Run apart, the child killed if it hangs.
    code = (
        "import os, sys, time, signal, drivescript as ds\n"
        "scene = ds.Scene.load(sys.argv[1])\n"
        "script = ds.CostScript.from_file(sys.argv[2], params={'cutter': 401, 'victim': 405})\n"
        "sampler = ds.Sampler(sys.argv[3])\n"
        "def work():\n"
        "    r = script.evaluate(scene, scene.log_future(40)).total\n"
        "    b = script.evaluate_batch(scene, scene.log_future(40)[None])[0].total\n"
        "    s = sampler.sample(scene, [script], samples=1, steps=8, polish=0).shape\n"
        "    return r, b, s\n"
        "parent = work()\n"
        "pid = os.fork()\n"
        "if pid == 0:\n"
        "    os._exit(0 if work() == parent else 3)\n"
        "t = time.time()\n"
        "while time.time() - t < 120:\n"
        "    done, status = os.waitpid(pid, os.WNOHANG)\n"
        "    if done:\n"
        "        print('child exit', os.waitstatus_to_exitcode(status))\n"
        "        sys.exit(0)\n"
        "    time.sleep(0.1)\n"
        "os.kill(pid, signal.SIGKILL)\n"
        "os.waitpid(pid, 0)\n"
        "print('child hung')\n"
    )
    import os
    import sys
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(sys.path))
    out = subprocess.run(
        [sys.executable, "-c", code, str(SCENE), str(CUT_IN), str(ROOT / "data/checkpoint")],
        capture_output=True, text=True, env=env, timeout=300,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "child exit 0", out.stdout + out.stderr[-2000:]


def test_a_constant_term_fails_validation_as_in_the_cli(ds, scene):
    flat = ds.CostScript.from_source('term("flat", 1.0);\n', name="flat.rhai")
    with pytest.raises(ds.ScriptError, match='flat.rhai:1: term "flat"') as e:
        flat.evaluate(scene, scene.log_future(10))
    assert e.value.line == 1 and e.value.column is None


def test_parameters_the_script_does_not_use_are_value_errors(ds):
    with pytest.raises(ValueError, match="cuttr"):
        ds.CostScript.from_file(CUT_IN, params={"cuttr": 401, "victim": 405})
    with pytest.raises(ValueError):
        ds.CostScript.from_file(CUT_IN, params={"cutter": [401], "victim": 405})


def test_a_script_from_source_reads_its_parameters_as_constants_as_from_a_file(ds, scene, tmp_path):
    # Parameters are constants in the script (docs/cost-scripts.md); from_source's syntax check
    # had none and refused every script reading one: "Undefined variable: cutter".
    source = 'term("x", agent(cutter).x.last());\n'
    (tmp_path / "x.rhai").write_text(source)
    traj = scene.log_future(10)
    by_source = ds.CostScript.from_source(source, params={"cutter": 401}).evaluate(scene, traj)
    by_file = ds.CostScript.from_file(tmp_path / "x.rhai", params={"cutter": 401})
    assert by_source.total == by_file.evaluate(scene, traj).total
    with pytest.raises(ds.ScriptError, match="syntax error"):
        ds.CostScript.from_source("let a = agent(cutter;\n", params={"cutter": 401})


def test_parameters_are_checked_as_the_cli_checks_param(ds, scene):
    # A NaN limit compared false with every speed: speed_limit scored 0 whatever the car did.
    limit = ROOT / "scripts/speed_limit.rhai"
    for bad, says in [(float("nan"), "NaN is not finite"), (float("inf"), "inf is not finite")]:
        with pytest.raises(ValueError, match=f'parameter "limit": {says}'):
            ds.CostScript.from_file(limit, params={"vehicle": 401, "limit": bad})
    with pytest.raises(ValueError, match="not a valid identifier"):
        ds.CostScript.from_source('term("x", agent(401).x.sum());', params={"a b": 1})
    with pytest.raises(ValueError, match="control character"):
        ds.CostScript.from_file(CUT_IN, params={"cutter": 401, "victim": 405, "turn": "l\x1b[2J"})
    # A name the checker does not read was dropped, the verdict taken for the default.
    with pytest.raises(ValueError, match='parameter "gapp": the checker does not read it'):
        ds.check("follow", scene, scene.log_future(40), {"leader": 401, "follower": 405, "gapp": 30})


def test_a_refused_parameter_value_is_quoted_cut_as_the_cli_quotes_one(ds, capfd):
    # Quoted whole (a 101-digit int, a 1,000-element list); an int beyond Python's 4,300
    # digits for str() said "<unprintable int object>" and printed an ignored exception's
    # traceback on stderr.
    for value, says in [
        (10**100, "1" + "0" * 63 + "… (101 characters)"),
        (10**5000, "an integer of 16610 bits"),
        ([1] * 1000, "(3000 characters)"),
    ]:
        with pytest.raises(ValueError) as e:
            ds.CostScript.from_file(CUT_IN, params={"cutter": value, "victim": 405})
        assert says in str(e.value) and len(str(e.value)) < 200, str(e.value)
    with pytest.raises(ValueError, match="parameter names are strings, got 1$"):
        ds.CostScript.from_file(CUT_IN, params={1: 2})
    assert "Exception ignored" not in capfd.readouterr().err


def test_a_path_holding_nul_is_refused_as_such(ds, scene, tmp_path):
    # Read as far as the format check: "unknown scene format", the NUL printed raw.
    bad = str(ROOT / "data/samples/yaml/highway_cut_in.yaml") + "\0x"
    for call in [
        lambda: ds.Scene.load(bad),
        lambda: ds.CostScript.from_file(bad),
        lambda: ds.Sampler(bad),
        lambda: scene.write_rollout(str(tmp_path / "r.json") + "\0", scene.log_future(10)),
    ]:
        with pytest.raises(ValueError, match=r"cannot hold the NUL character") as e:
            call()
        assert "\0" not in str(e.value) and "\\u{0000}" in str(e.value), str(e.value)
    assert list(tmp_path.iterdir()) == []


def test_nothing_to_evaluate_is_a_value_error_not_a_panic(ds, scene, cut_in, tmp_path):
    # crop(0, n) made a scene of no agents; evaluating on it panicked in the binding.
    for agents, future in [(0, 30), (8, 0)]:
        with pytest.raises(ValueError, match="at least one agent and one future step"):
            scene.crop(agents, future)
    empty = tmp_path / "empty.yaml"
    empty.write_text("steps: 91\ncurrent_step: 10\nroad: {lanes: 2, length: 300}\nagents: []\n")
    with pytest.raises(ValueError, match="no agents"):
        ds.Scene.load(empty)
    with pytest.raises(ValueError, match="steps = 0"):
        ds.suggest("cut_in", scene, 0)
    # A scene that ends at its current step (commonroad_current_step past the end is refused).
    ended_path = tmp_path / "ended.yaml"
    ended_path.write_text(
        (ROOT / "data/samples/yaml/highway_cut_in.yaml")
        .read_text()
        .replace("steps: 91", "steps: 11")
        # A lane change after the last step is refused on reading: it would not happen.
        .replace("    lane_change: {to: 1, start: 1.5, duration: 3.0}\n", "")
    )
    ended = ds.Scene.load(ended_path)
    with pytest.raises(ValueError, match="records no step after its current step"):
        ended.log_future()


def test_a_rollout_replaces_only_an_earlier_rollout(ds, scene, tmp_path):
    # write_rollout onto the scene it came from (or any file of the user's) replaced it.
    mine = tmp_path / "notes.json"
    mine.write_text((ROOT / "data/samples/yaml/highway_cut_in.yaml").read_text())
    with pytest.raises(ValueError, match="already exists and is not a rollout JSON"):
        scene.write_rollout(mine, scene.log_future(40))
    assert mine.read_text().startswith("# Three-lane highway")
    # Rollout JSON under a .yaml name (or none) was written as asked.
    for name in ["r.yaml", "r"]:
        with pytest.raises(ValueError, match="a rollout is JSON: give a name ending in .json"):
            scene.write_rollout(tmp_path / name, scene.log_future(40))
        assert not (tmp_path / name).exists()
    again = tmp_path / "r.json"
    scene.write_rollout(again, scene.log_future(40))
    scene.write_rollout(again, scene.log_future(30))
    assert len(json.loads(again.read_text())["agents"][0]["states"]) == scene.current_step + 31


def test_missing_or_malformed_files_are_os_and_value_errors(ds, tmp_path):
    with pytest.raises(FileNotFoundError):
        ds.Scene.load(tmp_path / "nope.xml")
    # A checkpoint directory that is not there was a ValueError.
    with pytest.raises(FileNotFoundError, match="no such checkpoint directory"):
        ds.Sampler(tmp_path / "nope")
    with pytest.raises(OSError):
        ds.CostScript.from_file(tmp_path / "nope.rhai")
    bad = tmp_path / "bad.yaml"
    bad.write_text("agents: [1, 2\n")
    with pytest.raises(ValueError, match="bad.yaml"):
        ds.Scene.load(bad)


def test_a_commonroad_current_step_for_another_format_is_a_value_error_not_ignored(ds):
    path = ROOT / "data/samples/yaml/highway_cut_in.yaml"
    with pytest.raises(ValueError, match="commonroad_current_step applies to CommonRoad scenes only"):
        ds.Scene.load(path, commonroad_current_step=3)
    assert ds.Scene.load(path).current_step == 10


def test_a_commonroad_current_step_past_the_scene_is_a_value_error_not_clamped(ds):
    path = ROOT / "data/samples/commonroad/USA_US101-3_3_T-1.xml"
    assert ds.Scene.load(path).current_step == 10
    assert ds.Scene.load(path, commonroad_current_step=20).current_step == 20
    n = ds.Scene.load(path).current_step + 1 + ds.Scene.load(path).future_steps
    # 2**64 - 1 wrapped to 0 in the check and loaded with no future.
    for k in [n - 1, n, 2**40, 2**64 - 1]:
        with pytest.raises(ValueError, match=f"commonroad_current_step {k} leaves no future"):
            ds.Scene.load(path, commonroad_current_step=k)


def test_a_script_given_twice_is_refused_as_simulate_refuses_it(ds, scene, cut_in):
    # It weighed twice, where `simulate --script F --script F` is refused.
    sampler = ds.Sampler(ROOT / "data/checkpoint")
    again = ds.CostScript.from_file(CUT_IN, params=CUT_IN_PARAMS)
    for twice in [[cut_in, cut_in], [cut_in, again]]:
        with pytest.raises(ValueError, match=r"scripts\[1\] is scripts\[0\] again .*each script counts once"):
            sampler.sample(scene, scripts=twice, samples=1, steps=8)


def test_a_bad_guidance_weight_names_the_keyword(ds, scene):
    sampler = ds.Sampler(ROOT / "data/checkpoint")
    for bad in [float("nan"), float("inf"), -1.0]:
        with pytest.raises(ValueError, match="sampler settings: guidance: lambda = "):
            sampler.sample(scene, samples=1, guidance=bad)
    # A weight with no script to weigh was dropped without a word, where `simulate --lambda 5`
    # with no --script is refused.
    with pytest.raises(ValueError, match="guidance = 5: no script to weigh"):
        sampler.sample(scene, samples=1, steps=8, guidance=5.0)
    assert sampler.sample(scene, samples=1, steps=8, polish=0, guidance=0.0).shape[0] == 1


def test_a_number_argument_out_of_range_or_of_another_type_is_named_in_the_message(ds, scene):
    # pyo3 named the argument only in an exception note, which Python before 3.11 never
    # shows and str(e) leaves out: "can't convert negative int to unsigned".
    sampler = ds.Sampler(ROOT / "data/checkpoint")
    cases = [
        (lambda: ds.Scene.load(SCENE, index=-1), ValueError, "index = -1: must be a whole number from 0 to"),
        (lambda: ds.Scene.load(SCENE, index=True), TypeError, "index = True: a bool, but index is an int"),
        (lambda: ds.Scene.load(SCENE, commonroad_current_step=1.5), TypeError, "commonroad_current_step = 1.5: a float"),
        (lambda: scene.log_future(10**400), ValueError, "(401 characters): must be a whole number from 0 to"),
        (lambda: scene.filled_future(-3), ValueError, "steps = -3: must be"),
        (lambda: scene.lane_path(2**70, 100.0), ValueError, "lane = 1180591620717411303424: must be a whole number from -9223372036854775808"),
        (lambda: scene.lane_path(1, 10**400), ValueError, "(401 characters): must be a number float64 holds"),
        (lambda: scene.agent_lane_path(401, "300"), TypeError, "length = '300': a str, but length is a number"),
        (lambda: scene.crop(-1, 40), ValueError, "agents = -1: must be"),
        (lambda: ds.suggest("cut_in", scene, steps=-1), ValueError, "steps = -1: must be"),
        (lambda: sampler.sample(scene, samples=0.5), TypeError, "samples = 0.5: a float, but samples is an int"),
        (lambda: sampler.sample(scene, seed=-1), ValueError, "seed = -1: must be a whole number from 0 to 18446744073709551615"),
        (lambda: sampler.sample(scene, horizon=-8), ValueError, "horizon = -8: must be"),
        (lambda: sampler.sample(scene, realism=10**400), ValueError, "(401 characters): must be a number float64 holds"),
        (lambda: sampler.sample(scene, polish=None), TypeError, "polish = None: a NoneType"),
    ]
    for call, kind, says in cases:
        with pytest.raises(kind) as e:
            call()
        assert says in str(e.value), str(e.value)
    # Numbers of other Python and numpy types still convert.
    assert scene.log_future(np.int64(10)).shape[1] == 10
    assert scene.agent_lane_path(np.int64(401), np.float32(50)).shape[1] == 2


def test_the_sampler_returns_samples_by_agents_by_steps_by_3(ds, scene, cut_in):
    sampler = ds.Sampler(ROOT / "data/checkpoint")
    a = sampler.sample(scene, scripts=[cut_in], samples=2, steps=8, polish=0)
    assert a.dtype == np.float64 and a.shape == (2, len(scene.agent_ids), sampler.horizon, 3)
    assert np.isfinite(a[~np.isnan(a)]).all() and (~np.isnan(a)).any()
    assert not np.array_equal(a[0], a[1], equal_nan=True)
    again = sampler.sample(scene, scripts=[cut_in], samples=2, steps=8, polish=0)
    assert np.array_equal(a, again, equal_nan=True), "the seed fixes the samples"
    with pytest.raises(ValueError, match="steps = 1"):
        sampler.sample(scene, steps=1)
    with pytest.raises(ValueError, match="task"):
        sampler.sample(scene, task="sideways")


def test_the_sampler_gives_the_samples_simulate_gives_for_the_same_settings(ds, scene, cut_in, cli, tmp_path):
    # Python guided through the denoiser after `simulate` had moved to output space (its
    # default): the same seed and settings gave other samples, without a word.
    out = tmp_path / "sim"
    cmd = [cli, "simulate", str(SCENE), "--script", str(CUT_IN), "--checkpoint",
           str(ROOT / "data/checkpoint"), "--samples", "1", "--steps", "8", "--polish", "0",
           "--seed", "3", "-o", str(out), "--param"]
    cmd += [f"{k}={v}" for k, v in CUT_IN_PARAMS.items()]
    subprocess.run(cmd, capture_output=True, text=True, check=True)
    docs = [json.loads(p.read_text()) for p in out.glob("*.json")]
    (r,) = [d for d in docs if d.get("format") == "drivescript-rollout"]
    a = ds.Sampler(ROOT / "data/checkpoint").sample(
        scene, scripts=[cut_in], samples=1, steps=8, polish=0, seed=3
    )[0]
    c = r["current_step"]
    by_id = {g["id"]: g["states"] for g in r["agents"]}
    compared = 0
    for i, agent in enumerate(scene.agent_ids):
        for k, st in enumerate(by_id.get(agent, [])[c + 1 : c + 1 + a.shape[1]]):
            if st[3]:
                assert np.allclose(a[i, k], st[:3], atol=1e-6), (agent, k, a[i, k], st)
                compared += 1
    assert compared > 0


def test_ctrl_c_stops_a_long_sampling_run_and_leaves_the_sampler_usable(ds, scene, cut_in):
    # 64 guided samples of 64 steps run for minutes on two cores; a Ctrl-C waited for them.
    sampler = ds.Sampler(ROOT / "data/checkpoint")
    interrupted_within(
        5.0, lambda: sampler.sample(scene, scripts=[cut_in], samples=64, steps=64)
    )
    a = sampler.sample(scene, scripts=[cut_in], samples=1, steps=8, polish=0)
    assert a.shape == (1, len(scene.agent_ids), sampler.horizon, 3)


def test_checkers_judge_trajectories_from_python(ds, scene):
    assert "cut_in" in ds.behaviours()
    v = ds.check("cut_in", scene, scene.log_future(40), CUT_IN_PARAMS)
    assert isinstance(v.passed, bool) and v.reason and set(v.named) <= {401, 405}
    with pytest.raises(ValueError, match="unknown behaviour"):
        ds.check("moonwalk", scene, scene.log_future(40), {})
    p = ds.suggest("cut_in", scene, 40)
    assert p is None or {"cutter", "victim"} <= set(p)


def test_rollouts_written_from_python_read_back_in_the_cli_s_format(scene, tmp_path):
    traj = scene.log_future(40)
    path = tmp_path / "r.json"
    scene.write_rollout(path, traj)
    doc = json.loads(path.read_text())
    assert doc["format"] == "drivescript-rollout" and len(doc["agents"]) == len(scene.agent_ids)
    assert len(doc["agents"][0]["states"]) == scene.current_step + 1 + 40


def test_help_is_useful(ds):
    assert "evaluate" in ds.CostScript.__doc__ or "evaluate" in (ds.CostScript.evaluate.__doc__ or "")
    for obj in [ds.Scene.load, ds.Scene.log_future, ds.CostScript.from_file, ds.CostScript.evaluate,
                ds.CostScript.evaluate_batch, ds.Sampler.sample, ds.check, ds.suggest, ds.torch.cost]:
        assert obj.__doc__ and len(obj.__doc__) > 40, obj


def test_a_huge_cost_is_shown_in_exponent_form(ds, scene):
    # Six decimals of a cost of 1e300 printed over 300 digits.
    big = ds.CostScript.from_source('term("big", agent(401).x.sum() + 1e300);')
    text = repr(big.evaluate(scene, scene.log_future(40)))
    assert re.search(r"total=\d\.\d{6}e\d+,", text) and len(text) < 200, text


def test_positions_beyond_any_map_are_a_value_error_not_an_internal_error(ds, scene, cut_in):
    # 1e300 is finite, but a checker's road-edge distance panicked on it ("internal error").
    far = np.full_like(scene.log_future(40), 1e300)
    for call in [
        lambda: ds.check("off_road", scene, far, params={"vehicle": 401}),
        lambda: cut_in.evaluate(scene, far),
    ]:
        with pytest.raises(ValueError, match="x is 1e300, beyond 1e7 m"):
            call()


def test_a_script_name_holding_a_line_break_or_a_bidi_control_is_refused(ds):
    # The name starts every error message: a newline in it faked a line of its own.
    for name, char in [("evil\nerror: all good", "U+000A"), ("x\u202ey", "U+202E")]:
        with pytest.raises(ValueError, match=re.escape(char)):
            ds.CostScript.from_source('term("x", agent(1).x.sum());', name=name)
    # A blank name began every message with a bare place: ":1:1: syntax error: ...".
    for name in ["", "  "]:
        with pytest.raises(ValueError, match="is blank"):
            ds.CostScript.from_source('term("x", agent(1).x.sum());', name=name)


def test_numpy_integers_and_text_that_is_no_utf8_as_parameters(ds, scene):
    # An id taken from an array of ids is a NumPy integer: it was refused as "not an int".
    ids = np.array(scene.agent_ids)
    by_numpy = ds.CostScript.from_file(CUT_IN, params={"cutter": ids[ids == 401][0], "victim": np.int32(405)})
    assert by_numpy.params == CUT_IN_PARAMS and type(by_numpy.params["cutter"]) is int
    # A lone surrogate raised UnicodeEncodeError naming no parameter (a value), or was said to
    # be no string at all (a name).
    with pytest.raises(ValueError, match='parameter "turn" = .*lone surrogate'):
        ds.CostScript.from_file(CUT_IN, params={"cutter": 401, "victim": 405, "turn": "l\udcff"})
    with pytest.raises(ValueError, match="parameter name .*lone surrogate"):
        ds.CostScript.from_file(CUT_IN, params={"cutter": 401, "victim": 405, "t\udcff": 1})


def test_a_str_argument_that_is_no_text_or_too_long_a_name_is_named(ds, scene, cut_in):
    # A lone surrogate (bytes that are not UTF-8, as os.fsdecode gives them) raised
    # "'utf-8' codec can't encode character", naming no argument; a name of 100,000
    # characters began every message of the script.
    bad = b"let x = 1;\xff".decode("utf-8", "surrogateescape")
    sampler = ds.Sampler(ROOT / "data/checkpoint")
    for call, arg in [
        (lambda: ds.CostScript.from_source(bad), "source"),
        (lambda: ds.CostScript.from_source("let x = 1;", name=bad), "name"),
        (lambda: scene.lane_path(1, 50.0, turn=bad), "turn"),
        (lambda: scene.agent_lane_path(401, turn=bad), "turn"),
        (lambda: ds.check(bad, scene, scene.log_future(40), CUT_IN_PARAMS), "behaviour"),
        (lambda: ds.suggest(bad, scene), "behaviour"),
        (lambda: sampler.sample(scene, task=bad), "task"),
    ]:
        with pytest.raises(ValueError, match=rf"^{arg} = .*: holds a lone surrogate, which is not text"):
            call()
    with pytest.raises(TypeError, match="^behaviour = 7: a int, but behaviour is a str"):
        ds.check(7, scene, scene.log_future(40), CUT_IN_PARAMS)
    with pytest.raises(ValueError, match="100000 characters; a script's name starts its error messages") as e:
        ds.CostScript.from_source("let x = ;", name="n" * 100_000)
    assert len(str(e.value)) < 300
    # The defaults still hold.
    assert ds.CostScript.from_source("let x = 1;").name == "<script>"
    assert scene.agent_lane_path(401).shape[1] == 2


def test_a_path_may_be_bytes_as_for_python_s_own_file_functions(ds, scene, tmp_path):
    # The TypeError for an int said "expected str, bytes or os.PathLike object", and bytes were
    # then refused: "'bytes' object is not an instance of 'str'".
    assert ds.Scene.load(bytes(SCENE)).agent_ids == scene.agent_ids
    assert ds.CostScript.from_file(bytes(CUT_IN), params=CUT_IN_PARAMS).name == str(CUT_IN)
    assert ds.Sampler(bytes(ROOT / "data/checkpoint")).horizon > 0
    out = tmp_path / "r.json"
    scene.write_rollout(bytes(out), scene.log_future(5))
    assert out.exists()
    with pytest.raises(TypeError, match="expected str, bytes or os.PathLike object, not int"):
        ds.Scene.load(123)


def test_a_batch_too_large_to_copy_is_a_value_error_not_the_oom_killer(ds, scene, cut_in):
    # A broadcast view holds no memory, but its items were copied and each given a gradient:
    # the process grew until the system's OOM killer ended it, with no exception.
    traj = scene.log_future(40)
    huge = np.broadcast_to(traj, (10**9,) + traj.shape)
    with pytest.raises(ValueError, match=r"more than evaluate_batch takes at once .* evaluate it in parts of at most \d+ items"):
        cut_in.evaluate_batch(scene, huge)
    # Still usable, and a batch under the cap runs.
    assert len(cut_in.evaluate_batch(scene, np.broadcast_to(traj, (3,) + traj.shape))) == 3
