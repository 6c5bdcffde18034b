"""The model's view of a stored scene: the one place that knows frame rates, history, future and slots.

Stores hold scenes at their stored rate (10 Hz, 101 frames, 33 slots). A model reads every `frame_stride`-th
stored frame (`num_frames` of them, the first `num_history` given), its first `num_agents` slots and
`num_map_tokens` map tokens per frame; a `velocity_inputs` model also reads each agent's instantaneous velocity
at the stored rate. `ModelSpec.view(scene)` takes that view; training, evaluation, validation, the public
rollout and the benchmark all go through it.

    spec = spec_from_config(config)             # horizons (3, 5, 8 s) as model frames; errors name the field
    model_scene = spec.view(stored_scene)       # Scene [..., T, A, ...] at the model's rate
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from gpd_jax.metrics.agents import horizon_label
from gpd_jax.scene import Scene

HORIZONS_S = (3.0, 5.0, 8.0)


class EvalError(ValueError):
    """Bad evaluation input (missing data, unknown task, shape mismatch, horizons that do not fit the model);
    the message names what and where."""


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """Static description of a model's view of stored scenes (hashable: a jit static argument).

    num_frames, num_history, num_agents, num_map_tokens: the model's T, H, A, M.
    frame_stride: model frame k is stored frame k * stride; stored_period_s: seconds between stored frames.
    horizons: future model frames of each scored horizon (e.g. (3, 5, 8) at 1 Hz).
    velocity_inputs: whether the model's scenes carry instantaneous velocities (see `view`).
    """

    num_frames: int
    num_history: int
    num_agents: int
    num_map_tokens: int
    frame_stride: int = 1
    stored_period_s: float = 0.1
    horizons: tuple[int, ...] = (30, 50, 80)
    velocity_inputs: bool = False

    def view(self, full: Scene) -> Scene:
        """The model's frames and slots of a stored-rate scene [..., T_stored, A_stored, ...] (with stored-rate
        velocities if the model takes them): a Scene [..., T, A, ...]."""
        period = self.stored_period_s if self.velocity_inputs else None
        return full.subsample(self.frame_stride, self.num_frames, self.num_agents, velocity_period_s=period)

    @property
    def frame_period_s(self) -> float:
        """Seconds between the model's frames."""
        return self.frame_stride * self.stored_period_s

    @property
    def num_future(self) -> int:
        return self.num_frames - self.num_history

    @property
    def current(self) -> int:
        """The current frame (last history frame), model-rate index."""
        return self.num_history - 1

    @property
    def labels(self) -> tuple[str, ...]:
        """Horizon labels ("3s", ...), one per `horizons` entry."""
        return tuple(horizon_label(h, self.frame_period_s) for h in self.horizons)

    @property
    def max_horizon(self) -> int:
        return max(self.horizons)

    @property
    def stored_frames_needed(self) -> int:
        return self.frame_stride * (self.num_frames - 1) + 1

    @property
    def full_history(self) -> int:
        """History frames of the stored-rate scene: stored frames [0, stride * (H - 1)] (the same current frame)."""
        return self.frame_stride * (self.num_history - 1) + 1

    def model_frames(self) -> slice:
        """The stored frames the model reads, as a slice of the stored frame axis."""
        return slice(0, self.stored_frames_needed, self.frame_stride)

    def future_stored_frames(self, count: int | None = None) -> np.ndarray:
        """Stored-frame indices of the first `count` (default: max horizon) future model frames."""
        count = self.max_horizon if count is None else count
        return self.frame_stride * (self.num_history + np.arange(count))


def horizon_frames(seconds: Sequence[float], frame_period_s: float, num_future: int
                   ) -> tuple[tuple[int, ...], tuple[float, ...]]:
    """Horizons in seconds -> (model frame counts that fit in `num_future`, the seconds that do not fit).

    Raises EvalError if a horizon is not a whole number of frames or none fits.
    """
    frames, skipped = [], []
    for s in seconds:
        f = s / frame_period_s
        n = int(round(f))
        if n <= 0 or abs(f - n) > 1e-6:
            raise EvalError(f"horizon {s:g} s is not a positive whole number of model frames "
                            f"(frame period {frame_period_s:g} s)")
        (frames if n <= num_future else skipped).append(n if n <= num_future else s)
    if not frames:
        raise EvalError(f"no horizon among {', '.join(f'{s:g} s' for s in seconds)} fits in the model's "
                        f"{num_future} future frames ({num_future * frame_period_s:g} s)")
    return tuple(sorted(set(frames))), tuple(skipped)


def model_frame_period_s(config) -> float:
    """Seconds between the model's frames: `data.frame_stride * data.frame_period_s`."""
    return int(config.data.frame_stride) * float(config.data.frame_period_s)


def spec_from_config(config, horizons_s: Sequence[float] = HORIZONS_S) -> tuple[ModelSpec, tuple[float, ...]]:
    """The ModelSpec of a full model config (its `model` and `data` sections) and the horizons (s) that do not
    fit in the model's future."""
    m, d = config.model, config.data
    stride, period = int(d.frame_stride), float(d.frame_period_s)
    if stride < 1:
        raise EvalError(f"config data.frame_stride must be >= 1, got {stride}")
    t, h = int(m.num_frames), int(m.num_history)
    frames, skipped = horizon_frames(horizons_s, stride * period, t - h)
    spec = ModelSpec(num_frames=t, num_history=h, num_agents=int(m.num_agents), num_map_tokens=int(m.num_map_tokens),
                     frame_stride=stride, stored_period_s=period, horizons=frames,
                     velocity_inputs=bool(m.velocity_inputs))
    return spec, skipped
