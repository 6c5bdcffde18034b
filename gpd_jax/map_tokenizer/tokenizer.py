"""The trained map tokenizer as pure functions of a params pytree (what the GPD model and the metrics use).

    tok = load_tokenizer("map_tokenizer")                          # a shipped tokenizer's name, or a folder
    tokens = jax.jit(tok.encode)(tok.params, rasters)          # f32[..., 256, 256] -> i32[..., 64]
    points, logits = jax.jit(tok.decode)(tok.params, tokens)   # -> f32[..., 50, 20, 2], f32[..., 50]
    tok.codebook                                               # f32[128, 128]

A checkpoint directory is either an exported tokenizer (`config.json` + `params.npz`, what ships in
`map_tokenizer`, found by name) or a training workdir (`config.json` + orbax `checkpoints/`; the latest step is
used). `export_tokenizer` writes the former (float16 by default, to keep the repository lean).
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import os
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from flax import nnx

from gpd_jax import zoo
from gpd_jax.config import config_from_json
from gpd_jax.fsutil import atomic_directory, flatten_params, load_params_npz, restore_params
from gpd_jax.map_tokenizer import core
from gpd_jax.map_tokenizer.model import MapVQVAE, build_vqvae
from gpd_jax.map_tokenizer.raster import cell_centres, from_ego_frame, raster_channels, rasterize, to_ego_frame


# The parameter groups that decide the tokens (the decoder does not): the encoder and the quantiser (a VQ codebook,
# or FSQ's projections, whose output projection is also the implied codebook the GPD embeds).
TOKEN_PARAMS = ("encoder/", "codebook/", "fsq/")


@dataclasses.dataclass(frozen=True, eq=False)
class MapTokenizer:
    """A map tokenizer: its config, the module structure (`graphdef`) and the params pytree."""

    config: ml_collections.ConfigDict
    graphdef: Any
    params: Any

    @property
    def codebook(self) -> jax.Array:
        """f32[K, D] the decoder input of each token id: the codebook, FSQ's implied one (what GPD embeds map
        tokens with)."""
        return core.code_table(self.graphdef, self.params)

    @property
    def num_tokens(self) -> int:
        return int(self.config.model.grid) ** 2

    def fingerprint(self) -> str:
        """16 hex digits identifying the tokens this tokenizer produces: a SHA-256 over the raster settings and
        the encoder and codebook parameters (float32; the decoder does not change tokens). An export and the
        workdir it came from share it. `raster.direction` False is the binary raster of configs written before
        that setting existed, so it hashes as absent (an export of a binary tokenizer keeps its fingerprint)."""
        raster = self.config.raster.to_dict()
        if not raster.get("direction", False):
            raster.pop("direction", None)
        h = hashlib.sha256(repr(sorted(raster.items())).encode())
        flat = flatten_params(jax.device_get(self.params))
        for k in sorted(flat):
            if k.startswith(TOKEN_PARAMS):
                a = np.ascontiguousarray(np.asarray(flat[k], np.float32))
                h.update(k.encode())
                h.update(repr(a.shape).encode())
                h.update(a.tobytes())
        return h.hexdigest()[:16]

    @property
    def reads_vectors(self) -> bool:
        """True for a vector tokenizer (`model.encoder.kind` "vector": it reads the lane polylines, no raster)."""
        return self.config.model.encoder.kind == "vector"

    def encode(self, params, rasters: jax.Array) -> jax.Array:
        """Map tokens i32[..., 64] (row-major over the 8x8 grid, row 0 = front) of rasters f32[..., 256, 256]
        (f32[..., 256, 256, 3] for a tokenizer with `raster.direction`). A raster tokenizer's only; every
        tokenizer encodes lanes (`encode_lanes`)."""
        if self.reads_vectors:
            raise ValueError("a vector map tokenizer (model.encoder.kind 'vector') reads lane polylines, not "
                             "rasters: use encode_lanes / encode_frames")
        k = 3 if raster_channels(self.config.raster) > 1 else 2
        lead = rasters.shape[:-k]
        r = rasters.reshape((-1,) + rasters.shape[rasters.ndim - k:]).astype(jnp.float32)
        z = core.encode_latents(self.graphdef, params, r)
        idx = core.tokens_of(self.graphdef, params, z)
        return idx.reshape(lead + (idx.shape[-1],))

    def encode_lanes(self, params, polylines: jax.Array, valid: jax.Array, pose: jax.Array) -> jax.Array:
        """Map tokens i32[..., 64] of lane polylines f32[..., L, P, 2] (bool[..., L, P] valid) seen from ego
        poses f32[..., 3] in the polylines' frame: rasterize (with this tokenizer's raster settings) + `encode`,
        exactly what `python -m gpd_jax.map_tokenizer encode` stores for a logged frame. A vector tokenizer reads
        the polylines themselves."""
        if self.reads_vectors:
            lead = pose.shape[:-1]
            flat = lambda x, k: jnp.broadcast_to(x, lead + x.shape[x.ndim - k:]).reshape((-1,) + x.shape[x.ndim - k:])
            z = core.encode_latents(self.graphdef, params, (flat(polylines, 3).astype(jnp.float32), flat(valid, 2),
                                                            flat(pose, 1).astype(jnp.float32)))
            idx = core.tokens_of(self.graphdef, params, z)
            return idx.reshape(lead + (idx.shape[-1],))
        r = self.config.raster
        raster = rasterize(polylines, valid, pose, size=r.size, pixel_size=r.pixel_size,
                           max_segment_length=r.max_segment_length, direction=raster_channels(r) > 1)
        return self.encode(params, raster)

    def pose_encoder(self, params):
        """`encode_lanes` with these parameters, as the `map_encoder` of `gpd_jax.decoding.rollout`: (polylines
        f32[L, P, 2], valid bool[L, P], pose f32[3]) -> i32[64]. Pass traced parameters (an argument of the
        jitted function) rather than constants, so they are not baked into the compiled rollout."""
        return lambda polylines, valid, pose: self.encode_lanes(params, polylines, valid, pose)

    def warper(self, params, margin_cells: float = 0.5):
        """A frame's map moved to a new ego pose, as the `map_warp` of `gpd_jax.decoding.rollout`: (tokens i32[64]
        seen from `from_pose` f32[3], `pose` f32[3], both in one scene frame) -> (tokens i32[64], new bool[64]).

        The tokens are decoded into lanes (those with logit > 0), moved into the scene frame, rasterized around
        `pose` and encoded again. `new[k]` marks the token cells the first window did not see: a cell is new
        where its centre, seen from `from_pose`, lies less than `margin_cells` cells inside that window's edge
        (0.5: the whole cell was seen, up to rotation), so its warped token holds no lanes there.
        """
        r, grid = self.config.raster, int(self.config.model.grid)
        half = r.size * r.pixel_size / 2.0
        cell = 2.0 * half / grid
        cells = cell_centres(grid, half)  # [64, 2]

        def warp(tokens, from_pose, pose):
            pts, logits = self.decode(params, tokens)
            valid = jnp.broadcast_to((logits > 0)[:, None], pts.shape[:-1])
            in_scene = from_ego_frame(pts, from_pose)
            warped = self.encode_lanes(params, in_scene, valid, pose)
            seen_before = to_ego_frame(from_ego_frame(cells, pose), from_pose)
            new = jnp.max(jnp.abs(seen_before), axis=-1) > half - margin_cells * cell + 0.01  # 1 cm: rounding
            return warped, new

        return warp

    def decode(self, params, tokens: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Vector lanes of tokens i32[..., 64]: (points f32[..., 50, 20, 2] metres in the frame's ego frame,
        existence logits f32[..., 50]; a line exists where logit > 0)."""
        lead = tokens.shape[:-1]
        t = tokens.reshape((-1, tokens.shape[-1]))
        model: MapVQVAE = nnx.merge(self.graphdef, params)
        pts, logits = model.decoder(jnp.take(model.code_table(), t, axis=0))
        return pts.reshape(lead + pts.shape[1:]), logits.reshape(lead + logits.shape[1:])

    def reconstruct(self, params, rasters: jax.Array) -> tuple[jax.Array, jax.Array]:
        """`decode(encode(rasters))`."""
        return self.decode(params, self.encode(params, rasters))

    def encode_frames(self, polylines, polyline_valid, poses) -> jax.Array:
        """Map tokens of every frame of a batch of scenes, compiled once per shape: the one way scenes get their
        missing map tokens (`gpd_jax.checkpoint.Model.prepare`). polylines f32[B, L, P, 2], polyline_valid
        bool[B, L, P] (scene frame), poses f32[B, T, 3] the ego of every frame -> i32[B, T, M]."""
        return _encode_frames(_structure(self), self.params, polylines, polyline_valid, poses)

    def decode_tokens(self, tokens) -> tuple[jax.Array, jax.Array]:
        """`decode` with this tokenizer's parameters, compiled once per shape: tokens i32[..., M] ->
        (points f32[..., Q, P, 2], existence logits f32[..., Q])."""
        return _decode_tokens(_structure(self), self.params, tokens)


def _structure(tok: MapTokenizer) -> MapTokenizer:
    """The one params-free `MapTokenizer` standing for every tokenizer with `tok`'s module structure and config:
    the static argument of the compiled `encode_frames` / `decode_tokens`. A `MapTokenizer` compares by identity,
    so keyed on `tok` itself every load of the same tokenizer (each a new object: every `encode` command, every
    `load_model`) traced and compiled those functions again for shapes already compiled."""
    key = (tok.graphdef, tok.config.to_json())
    if key not in _STRUCTURES:
        _STRUCTURES[key] = MapTokenizer(config=tok.config, graphdef=tok.graphdef, params=None)
    return _STRUCTURES[key]


_STRUCTURES: dict[tuple[Any, str], MapTokenizer] = {}


@functools.partial(jax.jit, static_argnames=("tok",))
def _encode_frames(tok: MapTokenizer, params, polylines, polyline_valid, poses):
    return jax.lax.map(lambda a: tok.encode_lanes(params, *a), (polylines, polyline_valid, poses))


@functools.partial(jax.jit, static_argnames=("tok",))
def _decode_tokens(tok: MapTokenizer, params, tokens):
    return tok.decode(params, tokens)


def export_tokenizer(params, config: ml_collections.ConfigDict, out_dir: str, dtype=np.float16,
                     exact: tuple[str, ...] = ("encoder", "codebook", "fsq")) -> None:
    """Writes `config.json` and `params.npz` to `out_dir` together (a temporary directory renamed into place;
    other files already in `out_dir`, such as a README or evaluation files, are kept).

    Parameters under the top-level keys `exact` stay float32 (so that the exported encoder gives exactly the
    tokens of the trained one); the others (the decoder) are cast to `dtype` to keep the file small.
    """
    with atomic_directory(out_dir) as tmp:
        with open(os.path.join(tmp, "config.json"), "w") as f:
            f.write(config.to_json(indent=2))
        flat = {k: v.astype(dtype) if v.dtype.kind == "f" and k.split("/")[0] not in exact else v
                for k, v in flatten_params(params).items()}
        np.savez_compressed(os.path.join(tmp, "params.npz"), **flat)


def load_tokenizer(name_or_path: str) -> MapTokenizer:
    """Loads a shipped tokenizer by name (`gpd_jax.list_models("map_tokenizer")`), an exported tokenizer or the
    latest checkpoint of a training workdir (see the module docstring)."""
    checkpoint_dir = zoo.resolve(name_or_path)
    cfg_path = os.path.join(checkpoint_dir, "config.json")
    if not os.path.isfile(cfg_path):
        raise FileNotFoundError(f"{checkpoint_dir} is not a map-tokenizer checkpoint (no config.json)")
    config = config_from_json(cfg_path)
    npz = os.path.join(checkpoint_dir, "params.npz")
    if os.path.isfile(npz):
        # Only shapes are needed to read an export: skip the (slow) random initialisation.
        model = nnx.eval_shape(lambda: build_vqvae(config, nnx.Rngs(0)))
        graphdef, state = nnx.split(model, nnx.Param)
        params = load_params_npz(npz, nnx.to_pure_dict(state))  # ValueError naming npz when it is damaged
    else:
        model = nnx.eval_shape(lambda: build_vqvae(config, nnx.Rngs(0)))
        graphdef, state = nnx.split(model, nnx.Param)
        try:
            params = restore_params(checkpoint_dir, nnx.to_pure_dict(state))
        except FileNotFoundError:
            raise FileNotFoundError(f"{checkpoint_dir} has neither params.npz nor orbax checkpoints") from None
    return MapTokenizer(config=config, graphdef=graphdef, params=params)
