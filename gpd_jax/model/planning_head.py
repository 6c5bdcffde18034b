"""The fine-tuned planning head of GPD-1 (paper Table 2: "we added only a single decoder layer to decode the ego
token"): one transformer decoder layer that reads a frame's output tokens and returns the ego's next F poses.

    head = PlanningHead(d_model=128, num_future=8, num_heads=4, ffn_dim=512, ego_slot=64, rngs=nnx.Rngs(0))
    plan = plan_trajectory(head, hidden)                 # hidden f32[..., N, d] -> f32[..., F, 3]
    plan = plan_trajectory(head, hidden, ego_pose)       # the same in the scene frame (ego_pose f32[..., 3])

The layer: F learned waypoint queries, each plus a projection of the ego token (and, with `route_points` > 0, an
MLP of where the route goes: `route_ahead`, the points every `route_spacing_m` metres along it), attend to each other
(self-attention), then to the frame's N tokens (cross-attention: map, ego and agents of the current frame,
whose hidden states already carry the history through the backbone's causal attention), then a GELU FFN
(pre-LN residual blocks, as the backbone's). A small MLP turns each query into (dx, dy, cos, sin): the
displacement from the previous waypoint (scaled by `position_scale` metres) and the heading as a unit vector.
Waypoint k is the running sum of the displacements, so positions start at the ego and grow smoothly.

With `candidates` ("idm"), the head chooses its plan among C candidate plans given with every call instead of
drawing it (PDM's idea, Dauner et al. 2023: a rule-based planner's candidates, here chosen by imitation): the same
layer, then a score per candidate, an MLP of the candidate's poses (over `position_scale`) plus a projection of the
mean of the waypoint queries; the plan is the best-scored candidate. The caller computes the candidates (IDM
along the route at C target speeds: `gpd_jax.sim.agents.idm_route_plan`) in the same ego frame; training teaches
the scores by the cross-entropy of the candidate closest to the log (`gpd_jax.training.planning`).

Frames: the head's output is in the ego frame of the frame whose tokens it read (origin at the ego's box
centre, x along its heading); `to_scene_frame` (or `plan_trajectory(..., ego_pose)`) turns it into the scene
frame. Output k (k = 0 .. F-1) is the ego at model frame t + 1 + k when the tokens are frame t's, at the
model's frame rate (1 s for the shipped models, so 8 frames = 8 s).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import nnx

from gpd_jax.scene import wrap_angle

CANDIDATES = ("", "idm")  # plan_head.candidates: "" the paper's head draws its plan; "idm": it chooses one


def _attend(q, k, v):
    """Multi-head softmax attention: q f32[..., Q, H, Dh], k, v f32[..., K, H, Dh] -> f32[..., Q, H, Dh]."""
    logits = jnp.einsum("...qhd,...khd->...hqk", q, k) / jnp.sqrt(jnp.asarray(q.shape[-1], q.dtype))
    return jnp.einsum("...hqk,...khd->...qhd", jax.nn.softmax(logits, axis=-1), v)


class PlanningHead(nnx.Module):
    """One decoder layer on the ego token -> the ego's next F poses (x, y, heading) in its current frame.

    Args:
      d_model: width of the backbone's tokens (the head works at the same width).
      num_future: F, poses planned (model frames after the one read).
      num_heads: attention heads of the self- and cross-attention.
      ffn_dim: hidden width of the FFN.
      ego_slot: index of the ego token among a frame's N tokens (M, the number of map tokens).
      position_scale: metres per unit of the displacement output (initial outputs are O(1)).
      rngs: parameter initialisation keys.
      route_points: R > 0 reads the route (the ego's frame, f32[..., R, 2]: `gpd_jax.geometry.route_ahead`); 0 the
        paper's head, without one.
      route_spacing_m: metres of route between those points.
      candidates: "" the paper's head (it draws the poses); "idm": it chooses one of `num_candidates` candidate
        plans given with every call (IDM along the route at several target speeds).
      num_candidates: C >= 2, candidate plans per call (a choosing head only).
    """

    def __init__(self, d_model: int, num_future: int, num_heads: int, ffn_dim: int, ego_slot: int,
                 rngs: nnx.Rngs, position_scale: float = 10.0, route_points: int = 0, route_spacing_m: float = 5.0,
                 candidates: str = "", num_candidates: int = 0):
        d = int(d_model)
        if d % int(num_heads):
            raise ValueError(f"plan_head: d_model {d} is not divisible by num_heads {num_heads}")
        if int(num_future) < 1:
            raise ValueError(f"plan_head.num_future must be >= 1, got {num_future}")
        self.num_future = int(num_future)
        self.num_heads = int(num_heads)
        self.ego_slot = int(ego_slot)
        self.position_scale = float(position_scale)
        self.route_points = int(route_points)
        self.route_spacing_m = float(route_spacing_m)
        if candidates not in CANDIDATES:
            raise ValueError(f"plan_head.candidates {candidates!r} is not one of {CANDIDATES}")
        self.candidates = str(candidates)
        self.num_candidates = int(num_candidates) if self.candidates else 0
        if self.candidates and self.num_candidates < 2:
            raise ValueError(f"plan_head: a head that chooses among candidate plans needs at least 2, got "
                             f"{num_candidates}")
        if self.route_points:
            self.route_in = nnx.Linear(2 * self.route_points, d, rngs=rngs)
            self.route_out = nnx.Linear(d, d, kernel_init=nnx.initializers.zeros, rngs=rngs)  # starts as no route
        self.queries = nnx.Param(0.02 * jax.random.normal(rngs.params(), (self.num_future, d)))
        self.ego_in = nnx.Linear(d, d, rngs=rngs)
        self.ln_mem = nnx.LayerNorm(d, rngs=rngs)
        self.ln_self = nnx.LayerNorm(d, rngs=rngs)
        self.self_qkv = nnx.Linear(d, 3 * d, rngs=rngs)
        self.self_out = nnx.Linear(d, d, rngs=rngs)
        self.ln_cross = nnx.LayerNorm(d, rngs=rngs)
        self.cross_q = nnx.Linear(d, d, rngs=rngs)
        self.cross_kv = nnx.Linear(d, 2 * d, rngs=rngs)
        self.cross_out = nnx.Linear(d, d, rngs=rngs)
        self.ln_ff = nnx.LayerNorm(d, rngs=rngs)
        self.ff1 = nnx.Linear(d, int(ffn_dim), rngs=rngs)
        self.ff2 = nnx.Linear(int(ffn_dim), d, rngs=rngs)
        self.ln_out = nnx.LayerNorm(d, rngs=rngs)
        if self.candidates:
            self.cand_in = nnx.Linear(3 * self.num_future, d, rngs=rngs)
            self.cand_ctx = nnx.Linear(d, d, rngs=rngs)
            self.cand_out = nnx.Linear(d, 1, rngs=rngs)
        else:
            self.out1 = nnx.Linear(d, d, rngs=rngs)
            self.out2 = nnx.Linear(d, 4, rngs=rngs)

    @classmethod
    def from_config(cls, head_cfg, model_cfg, rngs: nnx.Rngs) -> "PlanningHead":
        """The head of a full config's `plan_head` section for the backbone of its `model` section."""
        return cls(d_model=int(model_cfg.d_model), num_future=int(head_cfg.num_future),
                   num_heads=int(head_cfg.num_heads), ffn_dim=int(head_cfg.ffn_dim),
                   ego_slot=int(model_cfg.num_map_tokens), rngs=rngs,
                   position_scale=float(head_cfg.position_scale), route_points=int(head_cfg.route_points),
                   route_spacing_m=float(head_cfg.route_spacing_m), candidates=str(head_cfg.candidates),
                   num_candidates=len(head_cfg.idm_speeds))

    def _split(self, x):
        return x.reshape(x.shape[:-1] + (self.num_heads, x.shape[-1] // self.num_heads))

    def __call__(self, hidden, route=None, candidates=None):
        """hidden f32[..., N, d] (one frame's backbone outputs, before the backbone's final LayerNorm), route
        f32[..., R, 2] (a route head only: where the route goes, in that frame's ego frame), candidates f32[..., C,
        F, 3] (a choosing head only: the candidate plans in that frame's ego frame) -> f32[..., F, 3] (x, y,
        heading) in the ego frame of that frame: the drawn plan, or the best-scored candidate."""
        if candidates is None:
            self._check(hidden, route, candidates)
            out = self.out2(jax.nn.gelu(self.out1(self._decode(hidden, route))))        # [..., F, 4]
            xy = jnp.cumsum(out[..., :2] * self.position_scale, axis=-2)
            heading = jnp.arctan2(out[..., 3], out[..., 2] + 1.0)  # +1: heading 0 (straight on) at initialisation
            return jnp.concatenate([xy, heading[..., None]], axis=-1)
        pick = jnp.argmax(self.scores(hidden, route, candidates), axis=-1)
        return jnp.take_along_axis(candidates, pick[..., None, None, None], axis=-3)[..., 0, :, :]

    def scores(self, hidden, route, candidates):
        """A choosing head's score (logit) of each candidate plan: arguments as `__call__` -> f32[..., C]."""
        self._check(hidden, route, candidates)
        q = self._decode(hidden, route)                                                   # [..., F, d]
        cand = candidates.reshape(candidates.shape[:-2] + (3 * self.num_future,)) / self.position_scale
        ctx = self.cand_ctx(jnp.mean(q, axis=-2))[..., None, :]                          # [..., 1, d]
        return self.cand_out(jax.nn.gelu(self.cand_in(cand) + ctx))[..., 0]

    def _check(self, hidden, route, candidates):
        if hidden.ndim < 2 or hidden.shape[-2] <= self.ego_slot:
            raise ValueError(f"plan_head: hidden must be f32[..., N, d] with N > ego slot {self.ego_slot}, "
                             f"got shape {hidden.shape}")
        if (route is None) != (self.route_points == 0) or (
                route is not None and tuple(route.shape[-2:]) != (self.route_points, 2)):
            wants = (f"a route of {self.route_points} points (f32[..., {self.route_points}, 2])"
                     if self.route_points else "no route (plan_head.route_points is 0)")
            raise ValueError(f"plan_head: reads {wants}; got {None if route is None else tuple(route.shape)}")
        want = (self.num_candidates, self.num_future, 3)
        if (candidates is None) != (not self.candidates) or (
                candidates is not None and tuple(candidates.shape[-3:]) != want):
            wants = (f"{self.num_candidates} candidate plans ({self.candidates}, f32[..., "
                     f"{', '.join(map(str, want))}])" if self.candidates
                     else "no candidate plans (plan_head.candidates is empty)")
            raise ValueError(f"plan_head: reads {wants}; got "
                             f"{None if candidates is None else tuple(candidates.shape)}")

    def _decode(self, hidden, route):
        """The decoder layer: the F waypoint queries after it, layer-normed: f32[..., F, d]."""
        mem = self.ln_mem(hidden)
        ego = mem[..., self.ego_slot, :]
        q = self.queries[...] + self.ego_in(ego)[..., None, :]                    # [..., F, d]
        if route is not None:
            r = route.reshape(route.shape[:-2] + (2 * self.route_points,)) / self.position_scale
            q = q + self.route_out(jax.nn.gelu(self.route_in(r)))[..., None, :]
        s = self.self_qkv(self.ln_self(q))
        sq, sk, sv = (self._split(a) for a in jnp.split(s, 3, axis=-1))
        q = q + self.self_out(_attend(sq, sk, sv).reshape(q.shape))
        cq = self._split(self.cross_q(self.ln_cross(q)))
        ck, cv = (self._split(a) for a in jnp.split(self.cross_kv(mem), 2, axis=-1))
        q = q + self.cross_out(_attend(cq, ck, cv).reshape(q.shape))
        q = q + self.ff2(jax.nn.gelu(self.ff1(self.ln_ff(q))))
        return self.ln_out(q)


def to_scene_frame(plan, ego_pose):
    """Poses in the ego's frame -> the scene frame. plan f32[..., F, 3], ego_pose f32[..., 3] (x, y, heading of
    the ego in the scene frame) -> f32[..., F, 3], headings wrapped to [-pi, pi)."""
    c, s = jnp.cos(ego_pose[..., 2:3]), jnp.sin(ego_pose[..., 2:3])
    x, y = plan[..., 0], plan[..., 1]
    sx = ego_pose[..., 0:1] + c * x - s * y
    sy = ego_pose[..., 1:2] + s * x + c * y
    return jnp.stack([sx, sy, wrap_angle(plan[..., 2] + ego_pose[..., 2:3])], axis=-1)


def to_ego_frame(xy, heading, ego_pose):
    """Scene-frame poses -> the frame of `ego_pose`. xy f32[..., F, 2], heading f32[..., F], ego_pose f32[..., 3]
    -> f32[..., F, 3] (the inverse of `to_scene_frame`)."""
    c, s = jnp.cos(ego_pose[..., 2:3]), jnp.sin(ego_pose[..., 2:3])
    dx, dy = xy[..., 0] - ego_pose[..., 0:1], xy[..., 1] - ego_pose[..., 1:2]
    return jnp.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(heading - ego_pose[..., 2:3])], axis=-1)


def plan_trajectory(head, hidden, ego_pose=None, route=None, candidates=None):
    """The planned ego trajectory from one frame's backbone output tokens.

    Args:
      head: a `PlanningHead`, or a GPD module carrying one as `.plan_head` (`gpd_jax.load_model` of a plan-head
        checkpoint: `model.module`, or `nnx.merge(model.graphdef, params, model.rest)` inside a jitted function).
      hidden: f32[..., N, d] the frame's output tokens (map slots, then the ego at slot M, then agents), e.g.
        `gpd_jax.decoding.DecodeState.hidden` after the frame was appended.
      ego_pose: optional f32[..., 3] the ego's (x, y, heading) at that frame in the scene frame.
      route: f32[..., R, 2] for a head that reads the route (`PlanningHead.route_points` = R): where it goes, in
        the ego frame (`gpd_jax.geometry.route_ahead`).
      candidates: f32[..., C, F, 3] for a head that chooses among candidate plans (`PlanningHead.candidates`):
        those plans in the ego frame.
    Returns:
      f32[..., F, 3] (x, y, heading) of the ego at the next F model frames: in the ego's frame at the read
      frame, or in the scene frame when `ego_pose` is given.
    """
    head = getattr(head, "plan_head", head)
    if not isinstance(head, PlanningHead):
        raise TypeError(f"plan_trajectory needs a PlanningHead or a model with one (.plan_head), got "
                        f"{type(head).__name__}")
    plan = head(hidden, route, candidates)
    return plan if ego_pose is None else to_scene_frame(plan, ego_pose)
