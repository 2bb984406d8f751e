"""Type stubs of the compiled half of drivescript (see the package docstring)."""

from os import PathLike
from typing import Dict, List, Mapping, Optional, Sequence, Union

import numpy as np
import numpy.typing as npt

ParamValue = Union[int, float, bool, str]
AnyPath = Union[str, bytes, PathLike[str], PathLike[bytes]]
ArrayLike = npt.ArrayLike
F64Array = npt.NDArray[np.float64]

__version__: str

class ScriptError(Exception):
    """A cost script failed to compile, validate or evaluate; the message is the CLI's."""

    file: str
    """The script's name (its path for ``CostScript.from_file``)."""
    line: Optional[int]
    """1-based line, None where the error has none."""
    column: Optional[int]
    """1-based column, None where the error has none."""
    batch_index: int
    """Set by ``evaluate_batch``: the batch item that failed."""

class Scene:
    """A traffic scene: road map and agents' states at a fixed time step."""

    @staticmethod
    def load(
        path: AnyPath,
        index: int = 0,
        commonroad_current_step: Optional[int] = None,
    ) -> "Scene":
        """Reads scene ``index`` of ``path`` (every format the CLI reads). CommonRoad scenes
        start their future at ``commonroad_current_step`` (left out: 10, or a shorter scene's
        last step); given, it must leave at least one future step, and the scene must be
        CommonRoad's (other formats carry their own current step)."""
    @property
    def agent_ids(self) -> List[int]:
        """Agent ids, in the order of every trajectory array's agent axis."""
    @property
    def dt(self) -> float:
        """Seconds per step."""
    @property
    def current_step(self) -> int:
        """Index of the current step."""
    @property
    def future_steps(self) -> int:
        """Steps recorded after the current one."""
    @property
    def scenario_id(self) -> str:
        """The scenario's id."""
    def log_future(self, steps: Optional[int] = None) -> F64Array:
        """Recorded future, float64 ``[agents, steps, 3]`` (x, y, heading); NaN unobserved."""
    def filled_future(self, steps: Optional[int] = None) -> F64Array:
        """``log_future`` with unobserved states filled at constant velocity."""
    @property
    def agent_sizes(self) -> F64Array:
        """Each agent's length and width in metres, ``[agents, 2]``."""
    @property
    def agent_types(self) -> List[str]:
        """Each agent's type: "vehicle", "pedestrian", "cyclist" or "other"."""
    def lane_path(self, lane: int, length: float, turn: str = "straight") -> F64Array:
        """Centre line ``[points, 2]`` of a script's ``lane_path(lane, length, turn)``."""
    def agent_lane_path(
        self, agent_id: int, length: float = 300.0, turn: str = "straight"
    ) -> F64Array:
        """Centre line ``[points, 2]`` of a script's ``a.lane_path(length, turn)``."""
    def crop(self, agents: int, future: int) -> "Scene":
        """At most ``agents`` observed agents near a lane vehicle, ``future`` steps ahead."""
    def log_history(self) -> F64Array:
        """Recorded history up to the current step, ``[agents, current_step + 1, 3]``."""
    def write_rollout(self, path: AnyPath, traj: ArrayLike) -> None:
        """Writes ``traj`` as this scene's future in rollout JSON (atomically); ``path``
        must end in ``.json``."""

class CostResult:
    """One evaluation: total, per-term values and weights, gradient, prints."""

    total: float
    """Weighted total: sum of weight x value over the terms."""
    grad: F64Array
    """d total / d trajectories, shaped like them (0 where unobserved)."""
    prints: List[str]
    """Lines the script printed."""
    eval_ms: float
    """Milliseconds inside the engine."""
    @property
    def terms(self) -> Dict[str, float]:
        """Each term's unweighted value, in declaration order."""
    @property
    def weights(self) -> Dict[str, float]:
        """Each term's weight."""

class CostScript:
    """A sandboxed Rhai cost script with its parameters."""

    @staticmethod
    def from_file(
        path: AnyPath, params: Optional[Mapping[str, ParamValue]] = None
    ) -> "CostScript":
        """Reads a script file; unknown parameters raise ValueError."""
    @staticmethod
    def from_source(
        source: str, name: str = "<script>", params: Optional[Mapping[str, ParamValue]] = None
    ) -> "CostScript":
        """A script from source text (syntax checked now)."""
    @property
    def name(self) -> str:
        """Name used in messages."""
    @property
    def source(self) -> str:
        """Source text."""
    @property
    def params(self) -> Dict[str, ParamValue]:
        """Parameters."""
    def evaluate(self, scene: Scene, traj: ArrayLike) -> CostResult:
        """Evaluates on ``traj`` ``[agents, steps, 3]``."""
    def evaluate_batch(self, scene: Scene, trajs: ArrayLike) -> List[CostResult]:
        """Evaluates ``trajs`` ``[batch, agents, steps, 3]`` in parallel, GIL released."""

class Sampler:
    """The guided diffusion sampler with a checkpoint directory."""

    def __init__(self, checkpoint_dir: AnyPath) -> None: ...
    @property
    def horizon(self) -> int:
        """Future steps the model generates."""
    def sample(
        self,
        scene: Scene,
        scripts: Sequence[CostScript] = ...,
        samples: int = 4,
        *,
        seed: int = 1,
        steps: int = 32,
        task: str = "conditional",
        horizon: Optional[int] = None,
        guidance: float = ...,
        realism: float = ...,
        polish: int = ...,
    ) -> F64Array:
        """Guided samples, float64 ``[samples, agents, steps, 3]``, as ``simulate`` draws them.

        Runs with the GIL released; Ctrl-C stops it within one denoising step
        (KeyboardInterrupt)."""

class Verdict:
    """A behaviour checker's verdict."""

    passed: bool
    achieved: bool
    violations: List[str]
    measured: Dict[str, float]
    reason: str
    named: List[int]

def check(
    behaviour: str,
    scene: Scene,
    traj: ArrayLike,
    params: Optional[Mapping[str, ParamValue]] = None,
) -> Verdict:
    """Judges ``behaviour`` on ``scene`` with its future replaced by ``traj``."""

def suggest(
    behaviour: str, scene: Scene, steps: Optional[int] = None
) -> Optional[Dict[str, ParamValue]]:
    """Agents suited to ``behaviour``, as ``simulate --auto`` picks them, or None."""

def behaviours() -> List[str]:
    """Names of the behaviours the checkers know."""

def limits() -> Dict[str, float]:
    """The default resource limits of a cost script."""
