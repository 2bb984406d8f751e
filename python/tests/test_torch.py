"""ds.torch.cost: an autograd.Function whose backward is the engine's gradient."""

import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT

torch = pytest.importorskip("torch", reason="skipped: torch is not installed (pip install torch)")


def test_cost_is_the_total_and_backward_is_the_gradient(ds, scene, cut_in):
    traj = scene.log_future(40)
    r = cut_in.evaluate(scene, traj)
    t = torch.tensor(traj, requires_grad=True)
    cost = ds.torch.cost(cut_in, scene, t)
    assert cost.dim() == 0 and cost.dtype == torch.float64
    assert cost.item() == r.total
    cost.backward()
    assert np.array_equal(t.grad.numpy(), r.grad)


def test_a_batch_gives_one_cost_per_item_and_their_gradients(ds, scene, cut_in):
    traj = scene.log_future(40)
    batch = np.stack([traj, traj + np.array([0.5, -0.2, 0.0])])
    t = torch.tensor(batch, requires_grad=True)
    costs = ds.torch.cost(cut_in, scene, t)
    assert costs.shape == (2,)
    (costs * torch.tensor([1.0, 3.0], dtype=torch.float64)).sum().backward()
    for b, w in [(0, 1.0), (1, 3.0)]:
        r = cut_in.evaluate(scene, batch[b])
        assert costs[b].item() == r.total
        np.testing.assert_array_equal(t.grad[b].numpy(), w * r.grad)


def test_float32_in_float32_out(ds, scene, cut_in):
    t = torch.tensor(scene.log_future(40), dtype=torch.float32, requires_grad=True)
    cost = ds.torch.cost(cut_in, scene, t)
    cost.backward()
    assert cost.dtype == torch.float32 and t.grad.dtype == torch.float32


def test_complex_and_boolean_tensors_are_type_errors(ds, scene, cut_in):
    t = torch.tensor(scene.log_future(40))
    with pytest.raises(TypeError, match="complex"):
        ds.torch.cost(cut_in, scene, t.to(torch.complex128))
    with pytest.raises(TypeError, match="bool"):
        ds.torch.cost(cut_in, scene, t.isnan())


def test_what_is_not_a_tensor_is_a_type_error_naming_the_argument(ds, scene, cut_in):
    # "'numpy.ndarray' object has no attribute 'is_complex'" named neither.
    traj = scene.log_future(40)
    for bad, kind in [(traj, "numpy.ndarray"), (traj.tolist(), "builtins.list"), (None, "builtins.NoneType")]:
        with pytest.raises(TypeError, match=rf"^traj: a {kind}, but drivescript.torch.cost takes a torch.Tensor"):
            ds.torch.cost(cut_in, scene, bad)


def test_an_integer_tensor_is_a_type_error_not_a_truncated_cost(ds, scene, cut_in):
    # The cost came back in the tensor's dtype: 3.7 as 3, without a word.
    t = torch.tensor(scene.log_future(40)).nan_to_num().round().to(torch.int64)
    with pytest.raises(TypeError, match="torch.int64.*give a float tensor"):
        ds.torch.cost(cut_in, scene, t)


def test_a_cost_beyond_the_dtype_s_range_is_an_overflow_error_not_inf(ds, scene):
    # 70,000 is past float16's 65,504: the cost came back as inf.
    big = ds.CostScript.from_source(
        'term("far", abs(agent(401).x - 70000.0).mean());\n', name="big.rhai"
    )
    t = torch.tensor(scene.log_future(40), dtype=torch.float16, requires_grad=True)
    with pytest.raises(OverflowError, match="cost holds .*float16 .*65504"):
        ds.torch.cost(big, scene, t)
    assert torch.isfinite(ds.torch.cost(big, scene, t.detach().float()))


def test_a_second_derivative_is_refused_not_zero(ds, scene, cut_in):
    # The engine's gradient was taken for a constant: the Hessian came out as zeros.
    t = torch.tensor(scene.log_future(12))
    with pytest.raises(RuntimeError, match="a first derivative only"):
        torch.autograd.functional.hessian(lambda x: ds.torch.cost(cut_in, scene, x), t)
    x = t.clone().requires_grad_(True)
    with pytest.raises(RuntimeError, match="create_graph=True"):
        torch.autograd.grad(ds.torch.cost(cut_in, scene, x), x, create_graph=True)
    # The first derivative alone is as before.
    (g,) = torch.autograd.grad(ds.torch.cost(cut_in, scene, x), x)
    assert np.array_equal(g.numpy(), cut_in.evaluate(scene, t.numpy()).grad)


def test_gradcheck_in_float64(ds, scene, cut_in):
    # cut_in holds the victim (`hold(b)`: its gap and contact terms stop the victim's
    # gradient on purpose), so its exact Jacobian is checked w.r.t. the cutter. A short horizon keeps it quick.
    traj = scene.log_future(12)
    keep = ~np.isnan(traj).any(axis=(1, 2))
    rng = np.random.default_rng(2)
    traj[keep, :, :2] += rng.normal(0, 0.2, size=traj[keep, :, :2].shape)
    base = torch.tensor(traj)
    a = scene.agent_ids.index(401)
    assert keep[a]

    def cutter(x):
        t = base.clone()
        t[a] = x
        return ds.torch.cost(cut_in, scene, t)

    x = base[a].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(cutter, (x,), eps=1e-6, atol=1e-5, rtol=1e-4)

    # rightmost_lane holds nobody: checked w.r.t. every coordinate.
    rl = ds.CostScript.from_file(ROOT / "scripts/rightmost_lane.rhai", params={"vehicle": 405})
    assert rl.evaluate(scene, traj).total > 0
    t = torch.tensor(traj, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda x: ds.torch.cost(rl, scene, x), (t,), eps=1e-6, atol=1e-5, rtol=1e-4
    )


def test_adam_lowers_the_cost(ds, scene, cut_in):
    t = torch.tensor(scene.log_future(40), requires_grad=True)
    opt = torch.optim.Adam([t], lr=0.05)
    first = None
    for _ in range(20):
        opt.zero_grad()
        c = ds.torch.cost(cut_in, scene, t)
        first = c.item() if first is None else first
        c.backward()
        opt.step()
    assert ds.torch.cost(cut_in, scene, t).item() < first


def test_the_optimisation_example_ends_in_a_cut_in_that_the_checker_passes():
    out = subprocess.run(
        [sys.executable, str(ROOT / "python/examples/optimise_cut_in.py")],
        capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stderr
    assert 'checker on the optimised trajectories: Verdict(passed=True, reason="cuts in")' in out.stdout, out.stdout


needs_cuda = pytest.mark.skipif(
    not torch.cuda.is_available(), reason="skipped: no CUDA device (torch.cuda.is_available() is False)"
)


@needs_cuda
def test_a_cuda_tensor_gets_its_cost_and_gradient_on_its_device(ds, scene, cut_in):
    # Planners keep their trajectories on the GPU: the cost and its gradient come back there,
    # equal to the CPU's in float64 and within float32 rounding in float32.
    traj = scene.log_future(40)
    r = cut_in.evaluate(scene, traj)
    for dtype in (torch.float64, torch.float32):
        t = torch.tensor(traj, dtype=dtype, device="cuda", requires_grad=True)
        cost = ds.torch.cost(cut_in, scene, t)
        assert cost.device.type == "cuda" and cost.dtype == dtype
        cost.backward()
        assert t.grad.device.type == "cuda" and t.grad.dtype == dtype
        g = t.grad.cpu().double().numpy()
        if dtype == torch.float64:
            assert cost.item() == r.total
            assert np.array_equal(g, r.grad)
        else:
            r32 = cut_in.evaluate(scene, traj.astype(np.float32).astype(np.float64))
            assert cost.item() == pytest.approx(r32.total, rel=1e-6)
            np.testing.assert_allclose(g, r32.grad, rtol=1e-5, atol=1e-6)


@needs_cuda
def test_a_cuda_batch_and_gradcheck_on_the_device(ds, scene):
    rl = ds.CostScript.from_file(ROOT / "scripts/rightmost_lane.rhai", params={"vehicle": 405})
    traj = scene.log_future(12)
    keep = ~np.isnan(traj).any(axis=(1, 2))
    rng = np.random.default_rng(3)
    traj[keep, :, :2] += rng.normal(0, 0.2, size=traj[keep, :, :2].shape)
    batch = torch.tensor(np.stack([traj, traj + np.array([0.0, -1.0, 0.0])]), device="cuda", requires_grad=True)
    costs = ds.torch.cost(rl, scene, batch)
    assert costs.shape == (2,) and costs.device.type == "cuda"
    costs.sum().backward()
    for b in range(2):
        r = rl.evaluate(scene, batch[b].detach().cpu().numpy())
        assert costs[b].item() == r.total
        assert np.array_equal(batch.grad[b].cpu().numpy(), r.grad)
    t = torch.tensor(traj, device="cuda", requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: ds.torch.cost(rl, scene, x), (t,), eps=1e-6, atol=1e-5, rtol=1e-4)
