"""Hierarchical positional tokenizer for agents (GPD-1 §3.2), as pure functions.

Each coordinate p (x, y or heading) is shifted by an offset so that the representable range starts at 0 and is
quantized over N levels with scales s_1 > s_2 > ... > s_N (paper eqs. 3-4):

    q_1 = floor(p / s_1),    q_i = floor((p - sum_{j<i} q_j s_j) / s_i).

Each level index q_i gets a fixed sinusoidal code (true sinusoids, as the paper says; the official code
accidentally replaced them with frozen random tables) and the codes of all levels and coordinates are
concatenated. The learned MLP to the model width and the embedding of invisible agents live in the model.

Paper configuration: x and y in [-300, 300) m with levels {1 m, 0.01 m} (600 and 100 bins); heading in
[-180, 180) degrees with levels {20 deg, 1 deg} (18 and 20 bins). Values outside the representable range are
clamped (never indexed out of bounds) and `count_clamped` says how many were.

Optional extension (not in the paper; `model.velocity_inputs`): each agent's instantaneous velocity (vx, vy in
m/s) quantized the same way and appended, so a model at a low frame rate still sees current motion.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class LevelSpec:
    """Quantization of one coordinate.

    Attributes:
      offset: added before quantizing, so the representable range is [0, extent) after the shift.
      scales: level step sizes s_1 > ... > s_N, each an integer multiple of the next.
      code_dim: width of the sinusoidal code of each level index (even).
      unit: multiplier applied to the raw value first (e.g. 180/pi to quantize radians in degrees).
    """

    offset: float
    scales: tuple[float, ...]
    code_dim: int
    unit: float = 1.0

    @property
    def bins(self) -> tuple[int, ...]:
        """Number of indices per level: extent / s_1 for level 1, s_{i-1} / s_i below."""
        out = [int(round(2 * self.offset / self.scales[0]))]
        out += [int(round(a / b)) for a, b in zip(self.scales[:-1], self.scales[1:])]
        return tuple(out)

    @property
    def extent(self) -> float:
        return 2 * self.offset

    @property
    def dim(self) -> int:
        return self.code_dim * len(self.scales)


@dataclasses.dataclass(frozen=True)
class AgentTokenizer:
    """The full agent tokenizer: x, y (metres) and heading (radians) specs, and optionally a velocity spec
    (m/s, used for both components).

    `encode(xy f32[..., 2], heading f32[...][, velocity f32[..., 2]]) -> f32[..., dim]` is the concatenated
    sinusoidal code.
    """

    x: LevelSpec
    y: LevelSpec
    heading: LevelSpec
    velocity: LevelSpec | None = None

    @property
    def dim(self) -> int:
        v = 0 if self.velocity is None else 2 * self.velocity.dim
        return self.x.dim + self.y.dim + self.heading.dim + v

    @classmethod
    def from_config(cls, cfg) -> "AgentTokenizer":
        """Builds from a model config with fields xy_range, xy_levels, xy_code_dim, heading_levels_deg,
        heading_code_dim, and with `velocity_inputs` set also velocity_range, velocity_levels,
        velocity_code_dim."""
        xy = LevelSpec(offset=float(cfg.xy_range), scales=tuple(float(s) for s in cfg.xy_levels),
                       code_dim=int(cfg.xy_code_dim))
        hd = LevelSpec(offset=180.0, scales=tuple(float(s) for s in cfg.heading_levels_deg),
                       code_dim=int(cfg.heading_code_dim), unit=180.0 / math.pi)
        vel = None
        if cfg.velocity_inputs:
            vel = LevelSpec(offset=float(cfg.velocity_range), scales=tuple(float(s) for s in cfg.velocity_levels),
                            code_dim=int(cfg.velocity_code_dim))
        return cls(x=xy, y=xy, heading=hd, velocity=vel)

    def quantize(self, xy: jax.Array, heading: jax.Array):
        """Level indices: ((i32[..., Nx], i32[..., Ny], i32[..., Nh]), clamped bool[...])."""
        qx, cx = quantize(xy[..., 0], self.x)
        qy, cy = quantize(xy[..., 1], self.y)
        qh, ch = quantize(heading, self.heading)
        return (qx, qy, qh), cx | cy | ch

    def encode(self, xy: jax.Array, heading: jax.Array, velocity: jax.Array | None = None) -> jax.Array:
        """f32[..., dim] concatenated per-level sinusoidal codes of x, y, heading (and vx, vy when the
        tokenizer has a velocity spec, which then requires `velocity f32[..., 2]`)."""
        (qx, qy, qh), _ = self.quantize(xy, heading)
        codes = [level_codes(qx, self.x), level_codes(qy, self.y), level_codes(qh, self.heading)]
        if self.velocity is not None:
            if velocity is None:
                raise ValueError("this tokenizer encodes velocity: pass velocity f32[..., 2]")
            for c in range(2):
                codes.append(level_codes(quantize(velocity[..., c], self.velocity)[0], self.velocity))
        return jnp.concatenate(codes, axis=-1)

    def decode(self, qx, qy, qh):
        """Inverse of quantize: the lower corner of the finest cell (xy f32[..., 2], heading f32[...])."""
        x = dequantize(qx, self.x)
        y = dequantize(qy, self.y)
        h = dequantize(qh, self.heading)
        return jnp.stack([x, y], -1), h

    def count_clamped(self, xy: jax.Array, heading: jax.Array, valid: jax.Array | None = None) -> jax.Array:
        """i32[] number of (valid) agents whose x, y or heading lies outside the representable range."""
        _, clamped = self.quantize(xy, heading)
        if valid is not None:
            clamped = clamped & valid
        return jnp.sum(clamped.astype(jnp.int32))


def quantize(p: jax.Array, spec: LevelSpec):
    """Multi-level floor quantization of `p: f32[...]`.

    Returns (q i32[..., N] level indices, clamped bool[...]). Values outside the range are clamped into
    [0, extent) after the offset so indices never go out of bounds; non-finite values count as clamped.
    """
    v = jnp.asarray(p, jnp.float32) * spec.unit + spec.offset
    finest = spec.scales[-1]
    top = spec.extent - finest
    clamped = ~((v >= 0) & (v < spec.extent))
    v = jnp.where(jnp.isfinite(v), v, 0.0)
    v = jnp.clip(v, 0.0, top)
    # Work in integer units of the finest level to make the residual exact: round-off in floor(v/s) would
    # otherwise turn 0.30 into 29 centimetres.
    units = jnp.floor(v / finest + 1e-4).astype(jnp.int32)
    ratios = [int(round(s / finest)) for s in spec.scales]
    qs = []
    rest = units
    for r, n in zip(ratios, spec.bins):
        q = jnp.clip(rest // r, 0, n - 1)
        qs.append(q)
        rest = rest - q * r
    return jnp.stack(qs, axis=-1), clamped


def dequantize(q: jax.Array, spec: LevelSpec) -> jax.Array:
    """f32[...] value of level indices `q: i32[..., N]` (lower corner of the finest cell)."""
    scales = jnp.asarray(spec.scales, jnp.float32)
    return (jnp.sum(q.astype(jnp.float32) * scales, axis=-1) - spec.offset) / spec.unit


def sinusoid_table(num: int, dim: int, max_period: float = 10000.0) -> np.ndarray:
    """f32[num, dim] classic transformer position code: sin on even, cos on odd columns."""
    pos = np.arange(num, dtype=np.float64)[:, None]
    freqs = np.exp(-math.log(max_period) * np.arange(0, dim, 2, dtype=np.float64) / dim)[None, :]
    table = np.zeros((num, dim), np.float64)
    table[:, 0::2] = np.sin(pos * freqs)
    table[:, 1::2] = np.cos(pos * freqs)
    return table.astype(np.float32)


def level_codes(q: jax.Array, spec: LevelSpec) -> jax.Array:
    """f32[..., N * code_dim] sinusoidal code of each level index `q: i32[..., N]`, concatenated."""
    codes = []
    for i, n in enumerate(spec.bins):
        # The period scales with the number of bins so that neighbouring indices stay distinguishable at
        # every level (600 metre bins and 20 degree bins alike).
        table = jnp.asarray(sinusoid_table(n, spec.code_dim, max_period=max(4.0 * n, 10.0)))
        codes.append(jnp.take(table, q[..., i], axis=0))
    return jnp.concatenate(codes, axis=-1)
