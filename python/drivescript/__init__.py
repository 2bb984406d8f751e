"""drivescript: sandboxed, differentiable Rhai cost scripts for traffic scenes.

The cost engine, the guided diffusion sampler and the behaviour checkers of the drivescript
Rust library, for Python planners and simulators::

    import numpy as np, drivescript as ds
    scene = ds.Scene.load("data/samples/commonroad/USA_US101-4_1_T-1.xml")
    traj = scene.log_future(40)                      # float64 [agents, 40, 3], NaN unobserved
    script = ds.CostScript.from_file("scripts/cut_in.rhai", params={"cutter": 401, "victim": 405})
    r = script.evaluate(scene, traj)                 # r.total, r.terms, r.grad (like traj)
    rs = script.evaluate_batch(scene, np.stack([traj] * 64))   # parallel, GIL released
    cost = ds.torch.cost(script, scene, torch.tensor(traj, requires_grad=True))
    samples = ds.Sampler("data/checkpoint").sample(scene, scripts=[script], samples=4)

Errors in a script raise :class:`ScriptError` (with ``file``, ``line`` and ``column``) carrying
the CLI's message; an array of the wrong shape raises ``ValueError`` naming the shape wanted.
``drivescript.torch`` imports PyTorch only when called, so the package works without it.
"""

from ._native import (
    CostResult,
    CostScript,
    Sampler,
    Scene,
    ScriptError,
    Verdict,
    __version__,
    behaviours,
    check,
    limits,
    suggest,
)
from . import torch

__all__ = [
    "CostResult",
    "CostScript",
    "Sampler",
    "Scene",
    "ScriptError",
    "Verdict",
    "__version__",
    "behaviours",
    "check",
    "limits",
    "suggest",
    "torch",
]
