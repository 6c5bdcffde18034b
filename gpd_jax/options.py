"""How a rollout runs: one frozen, hashable options object, validated once and taken by the one jitted rollout.

    opts = gpd_jax.RolloutOptions(temperature=0.5, log_map="lanes")
    out = gpd_jax.rollout(model, scenes, "traffic_simulation", key, options=opts)
    fn = gpd_jax.make_rollout_fn(model, opts)          # the same rollout as a pure function of the parameters
    many = gpd_jax.RolloutOptions(temperature=1.0, samples=32)   # 32 sampled futures of each (scene, task)

The defaults are the paper's: greedy map tokens and regressed agents, the logged map tokens where the map comes
from the log, every generated map token the model's, the KV-cached rollout, one future per scene and task.
"""

from __future__ import annotations

import dataclasses
import math

LOG_MAPS = ("tokens", "lanes")
GEN_MAPS = ("model", "warp")
METHODS = ("cached", "recompute")


@dataclasses.dataclass(frozen=True)
class Sampling:
    """How a rollout draws what the model predicts as a distribution (hashable: static in the compiled rollout).

    temperature: 0 takes the most likely map token and each agent's regressed next state (the paper's); > 0 samples
      map tokens from their logits / temperature and, for a model with a sampling agent head (`model.agent_bins` >
      0), each agent's next state: a cell from its logits / temperature, then the cell's Laplace noise times the
      temperature (1: the model's own distribution).
    top_k: > 0 keeps only the k most likely map tokens / agent cells before sampling (0: all).
    top_p: < 1 keeps the smallest set of most likely ones whose probability reaches top_p (nucleus sampling).
    avoid_collisions: collision-aware decoding of a sampling head's agents (`gpd_jax.decoding.avoid_overlaps`): a
      generated agent whose next state (regressed at temperature 0, drawn above it) would overlap the box of an
      agent ahead of it (a pair already overlapping at the frame before is not tested), or leave the road its box
      was on (where the scene has road geometry), takes instead the cell of its sampling head nearest its state
      (temperature 0) or a drawn one (above it) that does neither; off by default (the model's own rollout).
    """

    temperature: float = 0.0
    top_k: int = 0
    top_p: float = 1.0
    avoid_collisions: bool = False

    def __post_init__(self):
        t = self.temperature
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or t < 0:
            raise ValueError(f"RolloutOptions.temperature must be a number >= 0, got {t!r}")
        object.__setattr__(self, "temperature", float(t))
        if isinstance(self.top_k, bool) or not isinstance(self.top_k, int) or self.top_k < 0:
            raise ValueError(f"RolloutOptions.top_k must be an integer >= 0 (0: no cut), got {self.top_k!r}")
        p = self.top_p
        if isinstance(p, bool) or not isinstance(p, (int, float)) or not 0 < p <= 1:
            raise ValueError(f"RolloutOptions.top_p must be a number in (0, 1], got {p!r}")
        object.__setattr__(self, "top_p", float(p))
        if not isinstance(self.avoid_collisions, bool):
            raise ValueError(f"RolloutOptions.avoid_collisions must be True or False, got {self.avoid_collisions!r}")

    @property
    def random(self) -> bool:
        """Whether anything is drawn at random (temperature > 0)."""
        return self.temperature > 0


@dataclasses.dataclass(frozen=True)
class RolloutOptions:
    """The choices of a rollout (hashable: a static argument of the compiled rollout).

    temperature, top_k, top_p: how map tokens and (with a sampling agent head) agents are sampled (`Sampling`:
      temperature 0, the default, takes the most likely map token and the regressed agent state).
    avoid_collisions: collision-aware decoding of the agents (`Sampling.avoid_collisions`; a sampling-head model).
    samples: None (one future per scene and task: outputs [S, K, ...]) or N >= 1: N futures of each, drawn with
      their own keys in the same compiled rollout (outputs [S, K, N, ...]; identical at temperature 0).
    log_map: where a task takes the map from the log but generates the ego (traffic simulation, motion planning):
      "tokens" feeds the logged map tokens (the paper's; they were encoded around the logged ego), "lanes" encodes
      the log's lanes around the generated ego every frame inside the rollout (needs the model's map tokenizer and
      the scenes' lane polylines).
    gen_map: where the map is generated: "model" (every token the model's, the paper's) or "warp" (the last given
      map moved with the ego, the model's tokens only in cells it did not see; needs the map tokenizer).
    method: "cached" (the KV-cached rollout: fast, not reverse-differentiable) or "recompute" (the official
      full-prefix forward every frame: slower; `jax.grad` goes through it).
    """

    temperature: float = 0.0
    top_k: int = 0
    top_p: float = 1.0
    log_map: str = "tokens"
    gen_map: str = "model"
    method: str = "cached"
    samples: int | None = None
    avoid_collisions: bool = False

    def __post_init__(self):
        sampling = self.sampling  # checks them
        object.__setattr__(self, "temperature", sampling.temperature)
        object.__setattr__(self, "top_p", sampling.top_p)
        n = self.samples
        if n is not None and (isinstance(n, bool) or not isinstance(n, int) or n < 1):
            raise ValueError(f"RolloutOptions.samples must be None or an integer >= 1, got {n!r}")
        for name, allowed in (("log_map", LOG_MAPS), ("gen_map", GEN_MAPS), ("method", METHODS)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"RolloutOptions.{name} must be one of {allowed}, got {getattr(self, name)!r}")

    @property
    def sampling(self) -> Sampling:
        """The temperature, top-k, top-p and collision-aware decoding as a `Sampling`."""
        return Sampling(self.temperature, self.top_k, self.top_p, self.avoid_collisions)

    @property
    def needs_tokenizer(self) -> bool:
        """Whether the rollout runs the model's map tokenizer (re-encoded log lanes, or a warped map)."""
        return self.log_map == "lanes" or self.gen_map == "warp"

    def replace(self, **changes) -> "RolloutOptions":
        return dataclasses.replace(self, **changes)
