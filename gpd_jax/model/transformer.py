"""The GPD-1 transformer (Flax NNX holds the parameters; the hot paths are pure functions of them).

A frame is N = M + A tokens in the order `[M map tokens | ego | A-1 agents]`. Every token gets a learned slot
embedding (N) and a learned frame embedding (T). Decoder blocks (pre-LN, GELU FFN) use the scene-level mask:
a token sees its own frame and all earlier frames. The output of a slot at frame t predicts the same slot at
frame t+1: position (2), heading (1), validity logit (1) for agent slots and K map logits for map slots.

Entry points (all single-scenario; `jax.vmap` them over scenarios and tasks):

* `GPD.embed(...)`: frame inputs -> tokens f32[F, N, d].
* `forward(model, tokens)`: teacher-forced pass over whole frames, memory-linear attention.
* `forward_cached(model, tokens, cache, start_frame)`: a block of frames appended to a KV cache.
* `predict(model, hidden, xy, heading, valid[, prev_xy, prev_valid][, velocity])`: heads -> `Prediction` for the
  next frame.

Option `velocity_inputs` (not in the paper): agent tokens also encode each agent's instantaneous velocity and a
fifth head predicts the next frame's velocity, which is fed back like positions. With `velocity_residual` the
position head then regresses the residual over xy + velocity * frame period, so a model at a low frame rate
extrapolates from current motion (as constant velocity at the stored rate does) instead of last frame's.

Option `agent_lane_residual` (not in the paper; needs `velocity_residual`, no parameters of its own): in the frames
where the model reads vector lanes (`LaneContext`: the log's `Scene.polylines` in the history and in frames whose
map is given, or a prompt's own lanes; frames whose map is generated get none, and training drops them from a share
of the scenes' future frames, `train.lane_context_drop`), the heads regress the residual over an agent that keeps
its lane instead of its straight line: the base position is where the agent lands after
covering constant velocity's step along the lane it is on, keeping its offset from the lane
(`gpd_jax.geometry.lane_follow`), and the base heading and velocity turn with the lane (`lane_base`). Agents
farther than `gpd_jax.geometry.LANE_SNAP_M` from a lane, and frames without lanes, keep the constant-velocity base.

Option `agent_bins` = w > 0 (not in the paper): a sampling head over each agent's next state beside the regression
heads (`Modes`): a categorical over the cells of a grid of w-metre cells of the next position's offset from the
regressed one, along and across the agent's heading (`bin_grid`), each cell a Laplace kernel of its spread, with the
regressed heading (and velocity) under one learned Laplace scale each: a mixture whose components are fixed to the
cells. A rollout at temperature 0 keeps the regressed state; at temperature > 0 it samples a cell and its noise
(`gpd_jax.decoding`). Training adds its negative log-likelihood of the logged next state (`gpd_jax.training.step`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from gpd_jax.geometry import lane_follow, rotate
from gpd_jax.model.attention import KERNELS, attend_dynamic, attend_static, dense_block_causal
from gpd_jax.scene import wrap_angle
from gpd_jax.model.agent_tokenizer import AgentTokenizer, sinusoid_table


@flax.struct.dataclass
class LaneContext:
    """The vector lanes an `agent_lane_residual` model's agents keep to (one scene; vmap for batches).

    polylines: f32[L, P, 2] directed lane centrelines in the scene frame; valid: bool[L, P];
    on: bool[F] per frame of the block being predicted from, whether its agents read the lanes (frames whose map
    is given), broadcast against the block's frames.
    """

    polylines: jax.Array
    valid: jax.Array
    on: jax.Array


class Frozen(nnx.Variable):
    """A non-trainable variable (the map codebook taken from the map tokenizer)."""


def bin_grid(width: float, extent: tuple[float, float]) -> np.ndarray:
    """f32[V, 2] the cell centres of an `agent_bins` head: offsets (along, across) from -extent to +extent metres in
    steps of `width` (both axes centred on 0), along-major."""
    along, across = (np.arange(-round(e / width), round(e / width) + 1) * width for e in extent)
    a, c = np.meshgrid(along, across, indexing="ij")
    return np.stack([a.ravel(), c.ravel()], -1).astype(np.float32)


def grid_code(grid: int, dim: int) -> np.ndarray:
    """f32[grid*grid, dim] fixed 2-D sinusoidal code of each cell (row code ++ column code), row-major."""
    half = dim // 2
    rows = sinusoid_table(grid, half, max_period=4.0 * grid)
    cols = sinusoid_table(grid, dim - half, max_period=4.0 * grid)
    r, c = np.meshgrid(np.arange(grid), np.arange(grid), indexing="ij")
    return np.concatenate([rows[r.ravel()], cols[c.ravel()]], axis=-1)


class MLP(nnx.Module):
    """Linear - LayerNorm - ReLU blocks then a final Linear (the official agent encoder and heads)."""

    def __init__(self, sizes: tuple[int, ...], rngs: nnx.Rngs, first_bias: bool = True):
        self.linears = nnx.List([nnx.Linear(a, b, use_bias=(i > 0 or first_bias), rngs=rngs)
                                 for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:]))])
        self.norms = nnx.List([nnx.LayerNorm(b, rngs=rngs) for b in sizes[1:-1]])

    def __call__(self, x):
        for lin, norm in zip(self.linears[:-1], self.norms):
            x = jax.nn.relu(norm(lin(x)))
        return self.linears[-1](x)


class Block(nnx.Module):
    """Pre-LN transformer block; attention itself is done by the caller so it can use a cache."""

    def __init__(self, d: int, heads: int, ffn: int, rngs: nnx.Rngs):
        if d % heads:
            raise ValueError(f"d_model {d} is not divisible by num_heads {heads}")
        self.heads = heads
        self.ln1 = nnx.LayerNorm(d, rngs=rngs)
        self.qkv = nnx.Linear(d, 3 * d, rngs=rngs)
        self.proj = nnx.Linear(d, d, rngs=rngs)
        self.ln2 = nnx.LayerNorm(d, rngs=rngs)
        self.ff1 = nnx.Linear(d, ffn, rngs=rngs)
        self.ff2 = nnx.Linear(ffn, d, rngs=rngs)

    def qkv_heads(self, x):
        """x f32[S, d] -> q, k, v f32[H, S, Dh] (head-major)."""
        s, d = x.shape
        qkv = self.qkv(self.ln1(x)).reshape(s, 3, self.heads, d // self.heads)
        qkv = jnp.transpose(qkv, (1, 2, 0, 3))
        return qkv[0], qkv[1], qkv[2]

    def finish(self, x, attn):
        """Residual updates given the attention output `attn f32[H, S, Dh]`."""
        x = x + self.proj(jnp.transpose(attn, (1, 0, 2)).reshape(x.shape))
        return x + self.ff2(jax.nn.gelu(self.ff1(self.ln2(x))))


MODE_HEAD = nnx.PathContains("mode_head")  # the parameters of the sampling head (`agent_bins`), as an NNX filter


class Modes(NamedTuple):
    """A mixture of C components over each agent's next state (the sampling head of `agent_bins` models: a component
    per cell).

    logits: f32[..., F, A, C] component logits; xy: f32[..., F, A, C, 2], heading: f32[..., F, A, C] and velocity
    f32[..., F, A, C, 2] (None without `velocity_inputs`) each component's centre; scale: f32[..., F, A, C, D] its
    Laplace scales of (along, across, heading[, v along, v across]) (m, rad, m/s), D = 3 or 5; axes: f32[..., F, A]
    the heading (rad) that "along" points to (each agent's input heading, 0 where the slot was invalid).
    """

    logits: jax.Array
    xy: jax.Array
    heading: jax.Array
    velocity: jax.Array | None
    scale: jax.Array
    axes: jax.Array

    def log_prob(self, xy, heading, velocity=None, velocity_known=None):
        """log density f32[..., F, A] of next states xy f32[..., F, A, 2], heading f32[..., F, A] (and velocity
        f32[..., F, A, 2] where `velocity_known` bool[..., F, A]; a model without velocities ignores them)."""
        err = [rotate(xy[..., None, :] - self.xy, -self.axes[..., None]),
               wrap_angle(heading[..., None] - self.heading)[..., None]]
        mask = [jnp.ones(err[0].shape, bool), jnp.ones(err[1].shape, bool)]
        if self.velocity is not None:
            err.append(rotate(velocity[..., None, :] - self.velocity, -self.axes[..., None]))
            mask.append(jnp.broadcast_to(velocity_known[..., None, None], err[-1].shape))
        err, mask = jnp.concatenate(err, -1), jnp.concatenate(mask, -1)
        per_dim = -jnp.log(2.0 * self.scale) - jnp.abs(err) / self.scale
        joint = jnp.sum(jnp.where(mask, per_dim, 0.0), -1)
        return jax.nn.logsumexp(jax.nn.log_softmax(self.logits, -1) + joint, -1)


class Prediction(NamedTuple):
    """Next-frame prediction of every slot of a block of frames.

    xy: f32[..., F, A, 2], heading: f32[..., F, A], valid_logit: f32[..., F, A], map_logits: f32[..., F, M, K],
    velocity: f32[..., F, A, 2] (m/s) for a `velocity_inputs` model, else None; modes: the sampling head's
    distribution over the agents' next states (`agent_bins` models), else None.
    """

    xy: jax.Array
    heading: jax.Array
    valid_logit: jax.Array
    map_logits: jax.Array
    velocity: jax.Array | None = None
    modes: Modes | None = None


DECODE_DTYPES = ("auto", "float32", "bfloat16")


def resolve_decode_dtype(name: str, backend: str | None = None):
    """`model.decode_dtype` as a dtype: "auto" is bfloat16 on an accelerator (GPU, TPU: half the cache bytes and the
    fused bf16 attention) and float32 on a CPU (no bf16 arithmetic there, so no faster; the shipped figures were
    computed in float32). docs/benchmarks.md has the measurements."""
    if name not in DECODE_DTYPES:
        raise ValueError(f"decode dtype {name!r}: expected one of {DECODE_DTYPES}")
    if name == "auto":
        name = "float32" if (backend or jax.default_backend()) == "cpu" else "bfloat16"
    return jnp.dtype(name)


@flax.struct.dataclass
class KVCache:
    """Keys and values per layer: k, v are tuples of L arrays f32[H, S, Dh] (S = frames * N padded to a chunk
    multiple; bf16 with `decode_dtype` bfloat16). One array per layer so that a scan carrying the cache updates each
    in place."""

    k: tuple[jax.Array, ...]
    v: tuple[jax.Array, ...]


class GPD(nnx.Module):
    """GPD-1 transformer. `cfg` is the `model` section of a config (see configs/gpd_paper.py).

    Args:
      cfg: model config.
      rngs: parameter initialisation keys.
      codebook: optional f32[K, D] map-tokenizer codebook; map tokens are then embedded as their (frozen)
        codebook vectors projected to d, otherwise with a learned K x d table.
      frame_period_s: seconds between the model's frames (velocity inputs turn into displacements with it).
    """

    def __init__(self, cfg, rngs: nnx.Rngs, codebook: np.ndarray | None = None, frame_period_s: float = 0.1):
        d = int(cfg.d_model)
        self.num_agents = int(cfg.num_agents)
        self.num_map = int(cfg.num_map_tokens)
        self.num_frames = int(cfg.num_frames)
        self.tokens_per_frame = self.num_map + self.num_agents
        self.chunk_len = int(cfg.attn_chunk_frames) * self.tokens_per_frame
        self.predict_delta = bool(cfg.predict_delta)
        self.dense_attention = cfg.train_attention == "dense"
        self.decode_attention = str(cfg.decode_attention)
        if self.decode_attention not in KERNELS:
            raise ValueError(f"model.decode_attention {self.decode_attention!r}: expected one of {KERNELS}")
        self.decode_dtype = str(cfg.decode_dtype)
        if self.decode_dtype not in DECODE_DTYPES:
            raise ValueError(f"model.decode_dtype {self.decode_dtype!r}: expected one of {DECODE_DTYPES}")
        self.velocity_residual = bool(cfg.velocity_residual)
        if self.velocity_residual and not self.predict_delta:
            raise ValueError("model.velocity_residual needs model.predict_delta")
        self.velocity_inputs = bool(cfg.velocity_inputs)
        self.lane_residual = bool(cfg.agent_lane_residual)
        if self.lane_residual and not self.velocity_residual:
            raise ValueError("model.agent_lane_residual needs model.velocity_residual (the step it moves along lanes)")
        self.frame_period_s = float(frame_period_s)
        self.tokenizer = AgentTokenizer.from_config(cfg)
        grid = int(round(math.sqrt(self.num_map)))
        if grid * grid != self.num_map:
            raise ValueError(f"num_map_tokens {self.num_map} is not a square grid")
        k_codes = int(cfg.codebook_size)

        self.agent_mlp = MLP((self.tokenizer.dim, d, d, d), rngs, first_bias=False)
        self.oob = nnx.Param(0.02 * jax.random.normal(rngs.params(), (d,)))
        if codebook is not None:
            codebook = np.asarray(codebook, np.float32)
            if codebook.shape[0] != k_codes:
                raise ValueError(f"codebook has {codebook.shape[0]} codes, config says {k_codes}")
            self.codebook = Frozen(jnp.asarray(codebook))
            self.map_in = nnx.Linear(codebook.shape[1], d, rngs=rngs)
        else:
            self.codebook = None
            self.map_embed = nnx.Embed(k_codes, d, rngs=rngs)
        self.grid_code = Frozen(jnp.asarray(grid_code(grid, d)))
        self.grid_mlp = nnx.Linear(d, d, rngs=rngs)
        self.slot_emb = nnx.Param(0.02 * jax.random.normal(rngs.params(), (self.tokens_per_frame, d)))
        self.frame_emb = nnx.Param(0.02 * jax.random.normal(rngs.params(), (self.num_frames, d)))
        self.blocks = nnx.List([Block(d, int(cfg.num_heads), int(cfg.ffn_dim), rngs)
                                for _ in range(int(cfg.num_layers))])
        self.final_ln = nnx.LayerNorm(d, rngs=rngs)
        hh = int(cfg.head_hidden)
        self.pos_head = MLP((d, hh, 2), rngs)
        self.heading_head = MLP((d, hh, 1), rngs)
        self.valid_head = MLP((d, hh, 1), rngs)
        self.map_head = MLP((d, hh, k_codes), rngs)
        self.velocity_head = MLP((d, hh, 2), rngs) if self.velocity_inputs else None
        self.bin_width = float(cfg.agent_bins)
        self.bin_extent = tuple(float(e) for e in cfg.agent_bin_extent)
        if self.bin_width < 0:
            raise ValueError(f"model.agent_bins must be >= 0, got {self.bin_width}")
        cells = len(bin_grid(self.bin_width, self.bin_extent)) if self.bin_width else 0
        # cell logits, then the Laplace scales of heading[, v along, v across]
        self.mode_head = MLP((d, hh, cells + 1 + 2 * self.velocity_inputs), rngs) if cells else None
        self.grid = grid
        self.lane_stride = int(cfg.lane_context_stride)

    # ------------------------------------------------------------------ embedding
    def embed(self, xy, heading, valid, map_tokens, frames, velocity=None):
        """Tokens of a block of frames.

        Args:
          xy: f32[F, A, 2], heading: f32[F, A], valid: bool[F, A], map_tokens: i32[F, M],
          frames: i32[F] absolute frame indices (for the frame embedding),
          velocity: f32[F, A, 2] (m/s), required by a `velocity_inputs` model and ignored otherwise.
        Returns:
          f32[F, N, d] with N = M + A, map tokens first.
        """
        codes = self.tokenizer.encode(xy, heading, self.input_velocity(velocity))
        agents = self.agent_mlp(codes)
        if self.codebook is not None:
            maps = self.map_in(jnp.take(self.codebook[...], map_tokens, axis=0))
        else:
            maps = self.map_embed(map_tokens)
        agents = jnp.where(valid[..., None], agents, self.oob[...])
        maps = maps + self.grid_mlp(self.grid_code[...])
        tokens = jnp.concatenate([maps, agents], axis=-2)
        return tokens + self.slot_emb[...] + jnp.take(self.frame_emb[...], frames, axis=0)[:, None, :]

    # ------------------------------------------------------------------ heads
    def input_velocity(self, velocity):
        """`velocity` for a `velocity_inputs` model (a clear error if it is None), None for any other model."""
        if not self.velocity_inputs:
            return None
        if velocity is None:
            raise ValueError("a velocity_inputs model needs each frame's velocity (Scene.velocity: build the "
                             "model's view with Scene.subsample(..., velocity_period_s=...))")
        return velocity

    @property
    def reads_lanes(self) -> bool:
        """Whether the model reads vector lanes (`agent_lane_residual`)."""
        return self.lane_residual

    def predict(self, hidden, xy, heading, valid, prev_xy=None, prev_valid=None, velocity=None,
                lanes: LaneContext | None = None) -> Prediction:
        """Next-frame predictions from hidden states `f32[F, N, d]` of frames whose inputs were
        xy f32[F, A, 2], heading f32[F, A], valid bool[F, A] (used when predicting displacements).

        With `velocity_residual`, `prev_xy f32[F, A, 2]` / `prev_valid bool[F, A]` are each frame's previous
        frame (invalid for frame 0): the position head then predicts the residual over constant velocity,
        xy + (xy - prev_xy) + head (plain displacement where the previous frame is missing). A
        `velocity_inputs` model takes `velocity f32[F, A, 2]` instead: the base is xy + velocity * frame period
        and the predicted velocity is velocity + its head's output (both plain where the slot is invalid).
        An `agent_lane_residual` model moves that base along the lanes of the frames where `lanes` has them
        (`lane_base`)."""
        h = self.final_ln(hidden)
        ha, hm = h[..., self.num_map:, :], h[..., : self.num_map, :]
        dxy = self.pos_head(ha)
        dh = self.heading_head(ha)[..., 0]
        turn = None
        if self.predict_delta:
            base = valid[..., None]
            pxy = dxy + jnp.where(base, xy, 0.0)
            step = None  # constant velocity's displacement over one frame
            if self.velocity_residual and self.velocity_inputs:
                step = jnp.where(base, self.input_velocity(velocity) * self.frame_period_s, 0.0)
            elif self.velocity_residual:
                if prev_xy is None or prev_valid is None:
                    raise ValueError("a velocity-residual model needs prev_xy and prev_valid")
                step = jnp.where((valid & prev_valid)[..., None], xy - prev_xy, 0.0)
            if step is not None:
                pxy = pxy + step
            heading_base = jnp.where(valid, heading, 0.0)
            if self.lane_residual and lanes is not None:
                lane_xy, turn, use = self.lane_base(xy, heading, valid, step, lanes)
                pxy = jnp.where(use[..., None], dxy + lane_xy, pxy)
                heading_base = heading_base + turn
            ph = wrap_angle(dh + heading_base)
        else:
            pxy, ph = dxy, wrap_angle(dh)
        pv = None
        if self.velocity_inputs:
            pv = self.velocity_head(ha)
            if self.velocity_residual:
                v = jnp.where(valid[..., None], self.input_velocity(velocity), 0.0)
                pv = pv + (v if turn is None else rotate(v, turn))
        modes = None if self.mode_head is None else self.modes(ha, pxy, ph, pv, jnp.where(valid, heading, 0.0))
        return Prediction(xy=pxy, heading=ph, valid_logit=self.valid_head(ha)[..., 0],
                          map_logits=self.map_head(hm), velocity=pv, modes=modes)

    def modes(self, ha, xy, heading, velocity, axes) -> Modes:
        """The sampling head on agent hidden states ha f32[F, A, d], around the regressed next state (xy f32[F, A, 2],
        heading f32[F, A], velocity f32[F, A, 2] or None): one component per cell of the grid of position offsets
        along / across `axes` f32[F, A] (`bin_grid`), a Laplace kernel of the cell's spread in position (scale
        w / sqrt(24): a w-wide uniform's variance), and the regressed heading and velocity with one learned scale
        each (heading, v along, v across)."""
        grid = jnp.asarray(bin_grid(self.bin_width, self.bin_extent))
        out = self.mode_head(ha)
        v = grid.shape[0]
        logits, raw = out[..., :v], out[..., v:]
        cell = jnp.full(raw.shape[:-1] + (2,), self.bin_width / math.sqrt(24.0))
        scale = jnp.concatenate([cell, jnp.exp(jnp.clip(raw, -7.0, 5.0))], -1)
        vel = None if velocity is None else jnp.broadcast_to(velocity[..., None, :], velocity.shape[:-1] + (v, 2))
        return Modes(logits=logits, xy=xy[..., None, :] + rotate(grid, axes[..., None]),
                     heading=jnp.broadcast_to(heading[..., None], heading.shape + (v,)), velocity=vel,
                     scale=jnp.broadcast_to(scale[..., None, :], scale.shape[:-1] + (v, scale.shape[-1])), axes=axes)

    def lane_base(self, xy, heading, valid, step, lanes: LaneContext):
        """Where each agent lands keeping its lane (`agent_lane_residual`): it covers |step| (f32[F, A, 2],
        constant velocity's displacement) along the lane it is on, from xy f32[F, A, 2] in the direction of step
        (its heading f32[F, A] when it stands), keeping its offset from the lane (`gpd_jax.geometry.lane_follow`).

        Returns (xy f32[F, A, 2], turn f32[F, A]: the lane's heading change over the step, zero where unused,
        use bool[F, A]: valid agents within `LANE_SNAP_M` of a lane in frames whose lanes are on). No gradient
        flows through it (the lanes and poses are inputs)."""
        xy = jax.lax.stop_gradient(jnp.where(valid[..., None], xy, 0.0))
        heading = jax.lax.stop_gradient(jnp.where(valid, heading, 0.0))
        step = jax.lax.stop_gradient(step)
        dist = jnp.sqrt(jnp.sum(step * step, axis=-1))
        direction = jnp.where(dist > 1e-6, jnp.arctan2(step[..., 1], step[..., 0]), heading)
        pts, turn, _, near = lane_follow(lanes.polylines, lanes.valid, xy, direction, dist, 1,
                                         stride=self.lane_stride)
        use = valid & near & jnp.broadcast_to(jnp.asarray(lanes.on, bool).reshape(-1, 1), valid.shape)
        return pts[..., 0, :], jnp.where(use, turn[..., 0], 0.0), use

    # ------------------------------------------------------------------ caches
    def padded_len(self, frames: int) -> int:
        s = frames * self.tokens_per_frame
        return -(-s // self.chunk_len) * self.chunk_len

    def cache_dtype(self):
        """The dtype of the rollout's KV cache and decode attention (`decode_dtype`, "auto" resolved for the
        default backend: `resolve_decode_dtype`)."""
        return resolve_decode_dtype(self.decode_dtype)

    def init_cache(self, frames: int | None = None, dtype=None) -> KVCache:
        """An empty cache for `frames` frames (default: the config's num_frames) of `dtype` (default:
        `cache_dtype()`)."""
        frames = self.num_frames if frames is None else frames
        dtype = self.cache_dtype() if dtype is None else dtype
        blk = self.blocks[0]
        d = blk.qkv.in_features
        shape = (blk.heads, self.padded_len(frames), d // blk.heads)
        return KVCache(k=tuple(jnp.zeros(shape, dtype) for _ in self.blocks),
                       v=tuple(jnp.zeros(shape, dtype) for _ in self.blocks))


def forward(model: GPD, tokens):
    """Teacher-forced pass over whole frames. tokens f32[F, N, d] -> hidden f32[F, N, d].

    Attention is chunked over keys with a flash-attention VJP: memory stays linear in F * N under autodiff.
    With `model.train_attention = "dense"` it is one masked [H, S, S] softmax instead: quadratic memory, but
    faster on a CPU for short sequences (XLA:CPU runs the chunk loop's elementwise work on one thread).
    """
    f, n, d = tokens.shape
    s = f * n
    x = tokens.reshape(s, d)
    if model.dense_attention:
        frame = jnp.arange(s) // n
        for blk in model.blocks:
            q, k, v = blk.qkv_heads(x)
            x = blk.finish(x, dense_block_causal(q, k, v, frame, frame))
        return x.reshape(f, n, d)
    pad = model.padded_len(f) - s
    for blk in model.blocks:
        q, k, v = blk.qkv_heads(x)
        k = jnp.pad(k, ((0, 0), (0, pad), (0, 0)))
        v = jnp.pad(v, ((0, 0), (0, pad), (0, 0)))
        x = blk.finish(x, attend_static(q, k, v, n, model.chunk_len))
    return x.reshape(f, n, d)


def forward_cached(model: GPD, tokens, cache: KVCache, start_frame):
    """Appends a block of frames to the cache and attends only to the filled chunks.

    Args:
      tokens: f32[F, N, d] tokens of frames [start_frame, start_frame + F).
      cache: KVCache holding frames [0, start_frame).
      start_frame: i32[] (may be traced).
    Returns:
      (hidden f32[F, N, d], updated cache).

    Keys and values are stored in the cache's dtype (bfloat16 with `decode_dtype` bfloat16); each attention path
    reads them as such (the XLA and cuDNN ones multiply in bf16 with float32 accumulation and softmax, the native
    CPU kernel widens them to float32); the residual stream, norms and heads stay float32.
    """
    f, n, d = tokens.shape
    s = f * n
    start = start_frame * n
    q_frame = start_frame + jnp.arange(s) // n
    num_chunks = (start + s + model.chunk_len - 1) // model.chunk_len
    x = tokens.reshape(s, d)
    ks, vs = [], []
    for i, blk in enumerate(model.blocks):
        q, k, v = blk.qkv_heads(x)
        kc = jax.lax.dynamic_update_slice_in_dim(cache.k[i], k.astype(cache.k[i].dtype), start, axis=1)
        vc = jax.lax.dynamic_update_slice_in_dim(cache.v[i], v.astype(cache.v[i].dtype), start, axis=1)
        ks.append(kc)
        vs.append(vc)
        attn = attend_dynamic(q, kc, vc, q_frame, num_chunks, n, model.chunk_len, model.decode_attention)
        x = blk.finish(x, attn.astype(x.dtype))
    return x.reshape(f, n, d), KVCache(k=tuple(ks), v=tuple(vs))


def reads_lanes(model_config) -> bool:
    """Whether a model of `model_config` reads vector lanes (`GPD.reads_lanes`, from the config alone)."""
    return bool(model_config.agent_lane_residual)


def samples_agents(model_config) -> bool:
    """Whether a model of `model_config` has a sampling agent head (`agent_bins`)."""
    return float(model_config.agent_bins) > 0


def count_params(model: nnx.Module) -> int:
    return sum(int(np.prod(x.shape)) for x in jax.tree.leaves(nnx.state(model, nnx.Param)))
