"""PyTorch autograd for drivescript cost scripts.

``cost(script, scene, traj)`` is differentiable: its backward pass is the gradient the Rust
engine computes with the value (dual numbers), so no graph of the script is built in PyTorch.
PyTorch is imported when ``cost`` is first called, not when ``drivescript`` is imported.
"""

from __future__ import annotations

from typing import Any

_Function: Any = None


def _function() -> Any:
    """The autograd.Function class, made on first use so that torch is imported lazily."""
    global _Function
    if _Function is not None:
        return _Function
    import numpy as np
    import torch

    class CostFunction(torch.autograd.Function):
        """Total cost of a script on trajectories; backward multiplies the engine's gradient."""

        @staticmethod
        def forward(ctx: Any, traj: "torch.Tensor", script: Any, scene: Any) -> "torch.Tensor":
            # `.to(float64)` would drop an imaginary part with only a warning.
            if traj.is_complex() or traj.dtype == torch.bool:
                raise TypeError(
                    f"traj: a tensor of {traj.dtype}, but positions and headings are real "
                    "numbers (a float dtype)"
                )
            # The cost and its gradient come back in traj's dtype: an integer tensor's cost
            # of 3.7 came back as 3, without a word.
            if not traj.is_floating_point():
                raise TypeError(
                    f"traj: a tensor of {traj.dtype}, but the cost and its gradient come back "
                    "in traj's dtype, which would cut them to whole numbers: give a float "
                    "tensor (traj.double())"
                )
            arr = traj.detach().to("cpu", torch.float64).contiguous().numpy()
            if arr.ndim == 4:
                results = script.evaluate_batch(scene, arr)
                total = np.array([r.total for r in results], dtype=np.float64)
                grad = np.stack([r.grad for r in results])
            else:
                r = script.evaluate(scene, arr)
                total = np.array(r.total, dtype=np.float64)
                grad = r.grad
            # A float64 figure past the range of traj's dtype became inf there (a cost of
            # 70,000 in float16), and the optimiser went on with it, without a word.
            out = torch.from_numpy(total).to(traj.device, traj.dtype)
            out_grad = torch.from_numpy(grad).to(traj.device, traj.dtype)
            for what, wide, narrow in [("cost", total, out), ("gradient", grad, out_grad)]:
                lost = np.isfinite(wide) & ~torch.isfinite(narrow).cpu().numpy()
                if lost.any():
                    worst = float(np.max(np.abs(wide[lost])))
                    raise OverflowError(
                        f"the {what} holds {worst:.6g}, beyond the range of traj's dtype "
                        f"{traj.dtype} (largest {torch.finfo(traj.dtype).max:.6g}), where it "
                        "would be inf: give traj as float32 or float64"
                    )
            ctx.save_for_backward(out_grad)
            return out

        @staticmethod
        def backward(ctx: Any, grad_output: "torch.Tensor") -> Any:
            # The engine's gradient comes back as numbers, not as a function of traj: a
            # second derivative through it (a Hessian, create_graph=True) came out as 0
            # without a word. Grad mode is on in a backward pass only when its graph is kept
            # for another derivative.
            if torch.is_grad_enabled():
                raise RuntimeError(
                    "drivescript.torch.cost has a first derivative only (the engine's gradient "
                    "comes back as numbers): a second one (create_graph=True, a Hessian) would "
                    "be 0 everywhere; take gradients with create_graph=False"
                )
            (grad,) = ctx.saved_tensors
            # One cost per batch item: broadcast each item's upstream gradient over its
            # trajectory.
            g = grad_output.reshape(grad_output.shape + (1,) * (grad.dim() - grad_output.dim()))
            return g * grad, None, None

    _Function = CostFunction
    return _Function


def cost(script: Any, scene: Any, traj: Any) -> Any:
    """The script's weighted total on ``traj`` as a differentiable tensor.

    ``traj`` is a tensor ``[agents, steps, 3]`` (a scalar comes back) or
    ``[batch, agents, steps, 3]`` (one cost per item, evaluated in parallel), any float dtype
    and device (complex, bool and integer dtypes are a ``TypeError``; a cost or gradient
    beyond the dtype's range an ``OverflowError``); it is evaluated in float64 on the CPU and the result and its gradient come
    back in ``traj``'s dtype and device. Unobserved states are NaN and get zero gradient.
    """
    fn = _function()
    import torch

    # An array or a list failed inside forward with "'numpy.ndarray' object has no attribute
    # 'is_complex'", naming neither the argument nor what it should be.
    if not isinstance(traj, torch.Tensor):
        raise TypeError(
            f"traj: a {type(traj).__module__}.{type(traj).__qualname__}, but "
            "drivescript.torch.cost takes a torch.Tensor (torch.tensor(traj)); "
            "script.evaluate(scene, traj) takes arrays"
        )
    return fn.apply(traj, script, scene)


__all__ = ["cost"]
