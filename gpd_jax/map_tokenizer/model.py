"""The map VQ-VAE: ResNet encoder to an 8x8 grid, a 128x128 codebook, and a DETR-style vector decoder.

Parameters live in Flax NNX modules; the hot paths (`encode_latents`, `quantize`, `decode_lines`) are used
as pure functions of a params pytree through `nnx.merge` (see `gpd_jax.map_tokenizer.tokenizer`).

Differences from the official GPD-1 deployment configuration (`reference/gpd_official.md` §4), all deliberate:
* GroupNorm replaces FrozenBatchNorm (no ImageNet weights here: the raster is a binary lane map, and batch
  statistics would make the encoder impure);
* the decoder is pre-norm (more stable from scratch) with learned query embeddings as the decoder input;
* the codebook is its own module (`MapVQVAE.codebook`), so the optimizer can give it its own learning rate.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from flax import nnx

from gpd_jax.map_tokenizer.raster import raster_channels, sine_position_2d
from gpd_jax.map_tokenizer.vector import VectorEncoder


def _groups(channels: int, max_groups: int) -> int:
    return math.gcd(channels, max_groups)


class ConvNorm(nnx.Module):
    """Conv (no bias) followed by GroupNorm."""

    def __init__(self, cin: int, cout: int, kernel: int, stride: int, groups: int, rngs: nnx.Rngs,
                 zero_scale: bool = False):
        self.conv = nnx.Conv(cin, cout, (kernel, kernel), strides=stride, padding="SAME", use_bias=False,
                             rngs=rngs)
        self.norm = nnx.GroupNorm(cout, num_groups=_groups(cout, groups), rngs=rngs,
                                  scale_init=nnx.initializers.zeros if zero_scale else nnx.initializers.ones)

    def __call__(self, x):
        return self.norm(self.conv(x))


class BasicBlock(nnx.Module):
    """Two 3x3 convs (ResNet-18/34 style)."""

    expansion = 1

    def __init__(self, cin: int, width: int, stride: int, groups: int, rngs: nnx.Rngs):
        cout = width * self.expansion
        self.c1 = ConvNorm(cin, width, 3, stride, groups, rngs)
        self.c2 = ConvNorm(width, cout, 3, 1, groups, rngs, zero_scale=True)
        self.proj = ConvNorm(cin, cout, 1, stride, groups, rngs) if (stride != 1 or cin != cout) else None

    def __call__(self, x):
        y = self.c2(jax.nn.relu(self.c1(x)))
        sc = self.proj(x) if self.proj is not None else x
        return jax.nn.relu(y + sc)


class BottleneckBlock(nnx.Module):
    """1x1 -> 3x3 (strided) -> 1x1 x4 (ResNet-50 style)."""

    expansion = 4

    def __init__(self, cin: int, width: int, stride: int, groups: int, rngs: nnx.Rngs):
        cout = width * self.expansion
        self.c1 = ConvNorm(cin, width, 1, 1, groups, rngs)
        self.c2 = ConvNorm(width, width, 3, stride, groups, rngs)
        self.c3 = ConvNorm(width, cout, 1, 1, groups, rngs, zero_scale=True)
        self.proj = ConvNorm(cin, cout, 1, stride, groups, rngs) if (stride != 1 or cin != cout) else None

    def __call__(self, x):
        y = self.c3(jax.nn.relu(self.c2(jax.nn.relu(self.c1(x)))))
        sc = self.proj(x) if self.proj is not None else x
        return jax.nn.relu(y + sc)


class Encoder(nnx.Module):
    """ResNet over a raster (`in_channels`: 1 binary, 3 directional), then GroupNorm -> 3x3 conv -> 3x3 conv to
    the code dim -> Linear.

    `cfg` fields: block ('basic' | 'bottleneck'), stage_sizes (blocks per stage), width (first stage width;
    doubles each stage), stem_patch (space-to-depth factor applied to the raster before the stem conv: a
    lossless reshape that makes CPU convolutions much cheaper; 1 = none, as in ResNet), stem_kernel,
    stem_stride, stem_pool (3x3/2 max-pool after the stem),
    stage_strides, norm_groups, head_channels, code_dim. The total stride must map 256 to the token grid.
    """

    def __init__(self, cfg: ml_collections.ConfigDict, rngs: nnx.Rngs, in_channels: int = 1):
        block = {"basic": BasicBlock, "bottleneck": BottleneckBlock}[cfg.block]
        g = cfg.norm_groups
        self.patch = int(cfg.stem_patch)
        self.in_channels = int(in_channels)
        self.stem = ConvNorm(self.patch ** 2 * self.in_channels, cfg.width, cfg.stem_kernel, cfg.stem_stride, g, rngs)
        self.stem_pool = bool(cfg.stem_pool)
        blocks = []
        cin = cfg.width
        for i, (n, s) in enumerate(zip(cfg.stage_sizes, cfg.stage_strides)):
            width = cfg.width * 2 ** i
            for j in range(n):
                blocks.append(block(cin, width, s if j == 0 else 1, g, rngs))
                cin = width * block.expansion
        self.blocks = nnx.List(blocks)
        self.head_norm = nnx.GroupNorm(cin, num_groups=_groups(cin, g), rngs=rngs)
        self.head_conv = nnx.Conv(cin, cfg.head_channels, (3, 3), padding="SAME", rngs=rngs)
        self.pre_quant = nnx.Conv(cfg.head_channels, cfg.code_dim, (3, 3), padding="SAME", rngs=rngs)
        self.out = nnx.Linear(cfg.code_dim, cfg.code_dim, rngs=rngs)

    def __call__(self, raster: jax.Array) -> jax.Array:
        """raster f32[B, H, W] (1 channel) or f32[B, H, W, C] -> latents f32[B, h, w, code_dim]."""
        x = raster[..., None] if self.in_channels == 1 and raster.ndim == 3 else raster
        if x.shape[-1] != self.in_channels:
            raise ValueError(f"the encoder takes {self.in_channels}-channel rasters, got shape {raster.shape}")
        if self.patch > 1:  # space to depth: channel index (i * p + j) * C + c
            b, h, w, c = x.shape
            p = self.patch
            x = x.reshape(b, h // p, p, w // p, p, c).transpose(0, 1, 3, 2, 4, 5).reshape(b, h // p, w // p,
                                                                                       p * p * c)
        x = self.stem(x)
        x = jax.nn.relu(x)
        if self.stem_pool:
            x = nnx.max_pool(x, (3, 3), strides=(2, 2), padding="SAME")
        for blk in self.blocks:
            x = blk(x)
        x = jax.nn.relu(self.head_norm(x))
        x = self.pre_quant(jax.nn.relu(self.head_conv(x)))
        return self.out(x)


class Codebook(nnx.Module):
    """The VQ codebook f32[K, D] (its own module so that it can get its own learning rate)."""

    def __init__(self, num_codes: int, code_dim: int, rngs: nnx.Rngs):
        self.embedding = nnx.Param(jax.random.uniform(rngs.params(), (num_codes, code_dim), jnp.float32,
                                                      -1.0 / num_codes, 1.0 / num_codes))


def nearest_code(codebook: jax.Array, z: jax.Array) -> jax.Array:
    """i32[...] index of the codebook row f32[K, D] nearest (L2) to each `z: f32[..., D]`."""
    d = (jnp.sum(z * z, -1, keepdims=True) - 2.0 * z @ codebook.T + jnp.sum(codebook * codebook, -1))
    return jnp.argmin(d, axis=-1).astype(jnp.int32)


def quantize(codebook: jax.Array, z: jax.Array, commitment: float = 0.25):
    """Vector quantization with a straight-through gradient.

    Args:
      codebook: f32[K, D].
      z: f32[..., D] encoder outputs.
      commitment: weight of the commitment term.

    Returns:
      (z_q f32[..., D] equal to the nearest codes in value, with the gradient of `z`;
       idx i32[...]; loss = mean|q - sg(z)|^2 + commitment * mean|sg(q) - z|^2).
    """
    idx = nearest_code(codebook, z)
    q = jnp.take(codebook, idx, axis=0)
    loss = jnp.mean((q - jax.lax.stop_gradient(z)) ** 2) + commitment * jnp.mean((jax.lax.stop_gradient(q) - z) ** 2)
    z_q = z + jax.lax.stop_gradient(q - z)
    return z_q, idx, loss


def fsq_round(h: jax.Array, levels: tuple[int, ...]) -> tuple[jax.Array, jax.Array]:
    """Finite scalar quantisation of `h: f32[..., d]` (d = len(levels)) with a straight-through gradient.

    Each dim is bounded by a shifted tanh into an interval of `levels[i]` integers and rounded: the integer
    q_i lies in [-(L_i // 2), (L_i - 1) // 2] (L_i levels, even L_i included). Returns (the rounded values
    divided by L_i // 2, in [-1, 1], f32[..., d], with the gradient of the bounded `h`; the levels' digits
    q_i + L_i // 2, i32[..., d], each in [0, L_i))."""
    L = jnp.asarray(levels, jnp.float32)
    # a hair wider than (L - 1) / 2, so that the shift below is finite for L = 2; the bound's overshoot (far below
    # half a level) never rounds to an (L_i + 1)-th level
    half = (L - 1.0) * (1.0 + 1e-3) / 2.0
    offset = jnp.where(jnp.asarray(levels) % 2 == 0, 0.5, 0.0)
    bounded = jnp.tanh(h + jnp.arctanh(offset / half)) * half - offset
    q = bounded + jax.lax.stop_gradient(jnp.round(bounded) - bounded)
    width = jnp.asarray([l // 2 for l in levels], jnp.float32)
    return q / width, (jnp.round(bounded) + width).astype(jnp.int32)


def fsq_index(digits: jax.Array, levels: tuple[int, ...]) -> jax.Array:
    """The mixed-radix token id i32[...] of level digits i32[..., d] (digit i in [0, levels[i]); the first
    dim is the most significant): a bijection onto [0, prod(levels))."""
    radix = [int(np.prod(levels[i + 1:], dtype=np.int64)) for i in range(len(levels))]
    return jnp.sum(digits * jnp.asarray(radix, jnp.int32), -1)


def fsq_values(idx: jax.Array, levels: tuple[int, ...]) -> jax.Array:
    """The normalised level values f32[..., d] (as `fsq_round` gives them) of token ids i32[...]."""
    digits, rest = [], idx
    for l in reversed(levels):
        digits.append(rest % l)
        rest = rest // l
    digits = jnp.stack(digits[::-1], -1).astype(jnp.float32)
    width = jnp.asarray([l // 2 for l in levels], jnp.float32)
    return (digits - width) / width


class FSQ(nnx.Module):
    """Finite scalar quantisation (Mentzer et al. 2023): a latent f32[..., D] is projected to d = len(levels)
    dims, each bounded and rounded to its levels (`fsq_round`), and projected back to D for the decoder. The
    token is the mixed-radix number of the levels (`fsq_index`), so the vocabulary is prod(levels), every code is
    reachable by construction and there is no codebook to learn, initialise or restart (no codebook loss, no
    k-means, no dead codes). `table()` is the implied codebook f32[prod(levels), D] (what the GPD embeds)."""

    def __init__(self, levels: tuple[int, ...], code_dim: int, rngs: nnx.Rngs):
        if len(levels) == 0 or any(int(l) < 2 for l in levels):
            raise ValueError(f"model.fsq_levels is {tuple(levels)}; expected a non-empty tuple of integers >= 2")
        self.levels = tuple(int(l) for l in levels)
        self.proj_in = nnx.Linear(code_dim, len(self.levels), rngs=rngs)
        self.proj_out = nnx.Linear(len(self.levels), code_dim, rngs=rngs)

    def __call__(self, z: jax.Array):
        """z f32[..., D] -> (z_q f32[..., D], idx i32[...], loss 0.0): `quantize`'s contract."""
        values, digits = fsq_round(self.proj_in(z), self.levels)
        return self.proj_out(values), fsq_index(digits, self.levels), jnp.zeros((), jnp.float32)

    def tokens(self, z: jax.Array) -> jax.Array:
        """Token ids i32[...] of latents f32[..., D]."""
        return fsq_index(fsq_round(self.proj_in(z), self.levels)[1], self.levels)

    def table(self) -> jax.Array:
        """f32[prod(levels), D]: the decoder input of every token id."""
        n = int(np.prod(self.levels))
        return self.proj_out(fsq_values(jnp.arange(n), self.levels))


class DecoderLayer(nnx.Module):
    """Pre-norm DETR decoder layer: self-attention over queries, cross-attention to the latent grid, FFN."""

    def __init__(self, d: int, heads: int, ffn: int, rngs: nnx.Rngs):
        self.n1 = nnx.LayerNorm(d, rngs=rngs)
        self.self_attn = nnx.MultiHeadAttention(heads, d, decode=False, rngs=rngs)
        self.n2 = nnx.LayerNorm(d, rngs=rngs)
        self.cross_attn = nnx.MultiHeadAttention(heads, d, decode=False, rngs=rngs)
        self.n3 = nnx.LayerNorm(d, rngs=rngs)
        self.ff1 = nnx.Linear(d, ffn, rngs=rngs)
        self.ff2 = nnx.Linear(ffn, d, rngs=rngs)

    def __call__(self, x, query_pos, memory, memory_pos):
        h = self.n1(x)
        x = x + self.self_attn(h + query_pos, h + query_pos, h, deterministic=True)
        h = self.n2(x)
        x = x + self.cross_attn(h + query_pos, memory + memory_pos, memory, deterministic=True)
        h = self.n3(x)
        return x + self.ff2(jax.nn.relu(self.ff1(h)))


class VectorDecoder(nnx.Module):
    """DETR-style lane decoder: `num_queries` learned line queries over the latent grid.

    Each query gives `num_points` points (tanh x `max_coord` metres) and an existence logit.
    """

    def __init__(self, cfg: ml_collections.ConfigDict, code_dim: int, grid: int, rngs: nnx.Rngs):
        d = cfg.d_model
        self.num_points = cfg.num_points
        self.max_coord = float(cfg.max_coord)
        self.grid = grid
        self.memory_in = nnx.Linear(code_dim, d, rngs=rngs)
        self.query_embed = nnx.Param(jax.random.normal(rngs.params(), (cfg.num_queries, d)) * 0.02)
        self.query_pos = nnx.Param(jax.random.normal(rngs.params(), (cfg.num_queries, d)) * 0.02)
        self.layers = nnx.List([DecoderLayer(d, cfg.num_heads, cfg.ffn_dim, rngs) for _ in range(cfg.num_layers)])
        self.norm = nnx.LayerNorm(d, rngs=rngs)
        self.points_head = nnx.Linear(d, cfg.num_points * 2, rngs=rngs)
        self.logit_head = nnx.Linear(d, 1, rngs=rngs)

    def _heads(self, x):
        x = self.norm(x)
        pts = jnp.tanh(self.points_head(x)) * self.max_coord
        pts = pts.reshape(x.shape[:-1] + (self.num_points, 2))
        return pts, self.logit_head(x)[..., 0]

    def __call__(self, latents: jax.Array):
        """latents f32[B, h*w, D] -> (points f32[B, Q, P, 2], logits f32[B, Q])."""
        b = latents.shape[0]
        memory = self.memory_in(latents)
        pos = sine_position_2d(self.grid, self.grid, memory.shape[-1])[None]
        x = jnp.broadcast_to(self.query_embed[...][None], (b,) + self.query_embed.shape)
        qpos = self.query_pos[...][None]
        for layer in self.layers:
            x = layer(x, qpos, memory, pos)
        return self._heads(x)


ENCODER_KINDS = ("raster", "vector")


class MapVQVAE(nnx.Module):
    """Encoder + codebook + vector decoder. `cfg` is the `model` section of a map-tokenizer config;
    `in_channels` the raster's (`gpd_jax.map_tokenizer.raster.raster_channels` of the config's `raster`), `half`
    half the window's side in metres (the vector encoder's window; the raster's is its size).

    `cfg.encoder.kind` picks the encoder: "raster" (the paper's ResNet over a lane raster: the encoder input is
    f32[B, 256, 256(, C)]) or "vector" (`gpd_jax.map_tokenizer.vector.VectorEncoder` over the lane polylines: the
    encoder input is the tuple (polylines f32[B, L, P, 2] scene frame, valid bool[B, L, P], pose f32[B, 3])).
    `cfg.fsq_levels` picks the quantiser: empty, the VQ codebook of `num_codes` learned codes (`Codebook`, the
    paper's); set, finite scalar quantisation (`FSQ`) with `num_codes` = the product of its levels."""

    def __init__(self, cfg: ml_collections.ConfigDict, rngs: nnx.Rngs, in_channels: int = 1, half: float = 32.0):
        self.grid = int(cfg.grid)
        self.commitment = float(cfg.commitment)
        kind = str(cfg.encoder.kind)
        if kind not in ENCODER_KINDS:
            raise ValueError(f"model.encoder.kind is {kind!r}; expected one of {ENCODER_KINDS}")
        self.encoder = (Encoder(cfg.encoder, rngs, in_channels) if kind == "raster" else
                        VectorEncoder(cfg.vector, self.grid, half, cfg.encoder.code_dim, rngs))
        levels = tuple(cfg.get("fsq_levels", ()) or ())
        if levels:
            if int(np.prod(levels)) != int(cfg.num_codes):
                raise ValueError(f"model.fsq_levels {tuple(levels)} give {int(np.prod(levels))} codes but "
                                 f"model.num_codes is {cfg.num_codes}: set it to their product")
            self.fsq = FSQ(levels, cfg.encoder.code_dim, rngs)
        else:
            self.codebook = Codebook(cfg.num_codes, cfg.encoder.code_dim, rngs)
        self.decoder = VectorDecoder(cfg.decoder, cfg.encoder.code_dim, self.grid, rngs)

    @property
    def uses_fsq(self) -> bool:
        """True when the quantiser is `FSQ` (`model.fsq_levels` set), False for the VQ codebook."""
        return hasattr(self, "fsq")

    def quantize(self, z: jax.Array):
        """(z_q f32[..., D] with a straight-through gradient, idx i32[...], quantiser loss) of latents z."""
        if self.uses_fsq:
            return self.fsq(z)
        return quantize(self.codebook.embedding[...], z, self.commitment)

    def tokens(self, z: jax.Array) -> jax.Array:
        """Token ids i32[...] of latents f32[..., D]."""
        return self.fsq.tokens(z) if self.uses_fsq else nearest_code(self.codebook.embedding[...], z)

    def code_table(self) -> jax.Array:
        """f32[K, D]: the decoder input of each of the K token ids (the codebook, or FSQ's implied one)."""
        return self.fsq.table() if self.uses_fsq else self.codebook.embedding[...]

    def encode_latents(self, inputs) -> jax.Array:
        """Encoder input (a raster f32[B, 256, 256] or [B, 256, 256, C], or the vector encoder's lane tuple; see
        the class docstring) -> continuous latents f32[B, grid*grid, D] (row-major cells)."""
        z = self.encoder(inputs)
        if isinstance(self.encoder, VectorEncoder):
            return z
        if z.shape[1:3] != (self.grid, self.grid):
            raise ValueError(f"encoder produced a {z.shape[1:3]} grid, config says {self.grid}x{self.grid}; "
                             "fix the strides")
        return z.reshape(z.shape[0], -1, z.shape[-1])

    def __call__(self, inputs, quantized: bool | jax.Array = True):
        """Full pass of an encoder input (see `encode_latents`). Returns dict(points, logits, idx i32[B, M], vq_loss,
        z f32[B, M, D]). `quantized` (a Python or
        traced bool) False feeds the continuous latents to the decoder and zeroes the VQ loss (training's
        continuous warm-up); `idx` are still the tokens of the latents."""
        z = self.encode_latents(inputs)
        z_q, idx, vq_loss = self.quantize(z)
        if quantized is not True:  # False, or a traced flag
            z_q = jnp.where(quantized, z_q, z)
            vq_loss = jnp.where(quantized, vq_loss, 0.0)
        points, logits = self.decoder(z_q)
        return dict(points=points, logits=logits, idx=idx, vq_loss=vq_loss, z=z)


def build_vqvae(config: ml_collections.ConfigDict, rngs: nnx.Rngs) -> MapVQVAE:
    """The `MapVQVAE` of a whole map-tokenizer config (its model, raster channels and window)."""
    r = config.raster
    return MapVQVAE(config.model, rngs, raster_channels(r), half=float(r.size) * float(r.pixel_size) / 2.0)
