"""How a rollout runs: one frozen, hashable options object, validated once and taken by the one jitted rollout.

    opts = gpd_jax.RolloutOptions(temperature=0.5, log_map="lanes")
    out = gpd_jax.rollout(model, scenes, "traffic_simulation", key, options=opts)
    fn = gpd_jax.make_rollout_fn(model, opts)          # the same rollout as a pure function of the parameters

The defaults are the paper's: greedy map tokens, the logged map tokens where the map comes from the log, every
generated map token the model's, the KV-cached rollout.
"""

from __future__ import annotations

import dataclasses
import math

LOG_MAPS = ("tokens", "lanes")
GEN_MAPS = ("model", "warp")
METHODS = ("cached", "recompute")


@dataclasses.dataclass(frozen=True)
class RolloutOptions:
    """The choices of a rollout (hashable: a static argument of the compiled rollout).

    temperature: 0 takes the most likely map token; > 0 samples map tokens at this temperature (with the key).
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
    log_map: str = "tokens"
    gen_map: str = "model"
    method: str = "cached"

    def __post_init__(self):
        t = self.temperature
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not math.isfinite(t) or t < 0:
            raise ValueError(f"RolloutOptions.temperature must be a number >= 0, got {t!r}")
        object.__setattr__(self, "temperature", float(t))
        for name, allowed in (("log_map", LOG_MAPS), ("gen_map", GEN_MAPS), ("method", METHODS)):
            if getattr(self, name) not in allowed:
                raise ValueError(f"RolloutOptions.{name} must be one of {allowed}, got {getattr(self, name)!r}")

    @property
    def needs_tokenizer(self) -> bool:
        """Whether the rollout runs the model's map tokenizer (re-encoded log lanes, or a warped map)."""
        return self.log_map == "lanes" or self.gen_map == "warp"

    def replace(self, **changes) -> "RolloutOptions":
        return dataclasses.replace(self, **changes)
