"""Store-level augmentation: the mirror image of every scene of a store, and the scenes as a vehicle's sensors
would see them.

`mirror_store(src, dst)` reflects each sample across the x axis of its scene frame (x forward, y left): every
point's y and every heading change sign, so roads curve the other way and right-hand traffic becomes left-hand
traffic on mirrored roads. The reflection is exact (no resampling) and applied to every geometry key together
(agents, ego poses, lane polylines, drivable area, road edges), so the scene stays consistent; sizes and types
are unchanged. Map tokens are not carried over (the tokenizer is not mirror-equivariant): encode the new store
(`python -m gpd_jax.map_tokenizer encode --data DST ...`). Shards are written atomically and a rerun skips the
ones already there.

Why: a model that trains long on a handful of real road networks memorizes their geometry
(docs/results.md); mirroring doubles the geometry of the
networks there are, and is the left-hand traffic that real logs from Singapore or the UK hold.

`sensor_store(src, dst, SensorView(...))` keeps the ego (slot 0, whose pose a vehicle knows) and the maps and
shows every other agent as an on-board tracker would: a slowly drifting position and heading error (AR(1) per
stored frame), only within a range of the ego, and with short gaps where the track is lost (occlusion). Map
tokens are carried over (the ego and the maps are unchanged). Recorded drone traffic (INTERACTION) and SUMO
have none of this, logs from vehicles (nuScenes, Waymo, nuPlan) all of it: a sensor view of a development store
asks how a model trained on clean tracks holds up on them (docs/results.md, 2026-11-29).
"""

from __future__ import annotations

import dataclasses
import os
import zlib

import numpy as np

from gpd_jax.data import store
from gpd_jax.data.errors import DataError
from gpd_jax.data.roadgeom import ROAD_KEYS

# f32[..., 2] points in the scene frame
POINT_KEYS = ("xy", "polylines", "road_polygons", "road_edges", "road_map_edges", "signal_stop", "signal_lane")
SUFFIX = "/mirror"


def _wrap(a: np.ndarray) -> np.ndarray:
    return ((a + np.pi) % (2 * np.pi) - np.pi).astype(a.dtype)


def reverse_prefix(points: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """`points f[..., P, 2]` with each row's valid prefix (`valid bool[..., P]`) in reverse order (padding kept)."""
    n = valid.sum(-1, keepdims=True)
    idx = np.arange(valid.shape[-1])
    src = np.where(idx < n, n - 1 - idx, idx)
    return np.take_along_axis(points, src[..., None], axis=-2)


def mirror_arrays(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The mirror image (y -> -y, heading -> -heading) of a shard's (or a sample's) arrays; keys it does not know
    are copied unchanged."""
    out = {k: np.array(v, copy=True) for k, v in arrays.items()}
    for k in POINT_KEYS:
        if k in out:
            out[k][..., 1] *= -1
    if "road_map_edges" in out:  # a reflection turns the drivable side to the right: run each edge backwards
        out["road_map_edges"] = reverse_prefix(out["road_map_edges"], out["road_map_edge_valid"])
    if "heading" in out:
        out["heading"] = _wrap(-out["heading"])
    if "ego_pose" in out:
        out["ego_pose"][..., 1] *= -1
        out["ego_pose"][..., 2] = _wrap(-out["ego_pose"][..., 2])
    return out


def _transform_store(src: str, dst: str, splits: list[str] | None, fn, suffix: str, meta_fn, made: str,
                     keep_tokens: bool) -> None:
    """Writes `fn(arrays, split, shard index)` of every shard of `splits` (default: all) of store `src` into store
    `dst` with the same shard indices, scenario ids and locations suffixed, `meta_fn(meta)` merged into the shard
    meta with `"{made}_from"`, and (`keep_tokens`) the source's map tokens and their record copied beside. Shards
    already in dst are skipped (their tokens copied if missing): a rerun resumes."""
    if os.path.abspath(src) == os.path.abspath(dst):
        raise DataError(dst, f"the {made} store must be a new directory, not the source")
    for split in splits or store.list_splits(src):
        indices = store.shard_indices(src, split)
        if not indices:
            raise DataError(os.path.join(src, split), f"no complete shards in split {split!r} to read")
        for j in indices:
            out = store.shard_dir(dst, split, j)
            written = os.path.isdir(out)  # by an earlier run
            if written and not keep_tokens:
                continue
            sh = store.Shard(store.shard_dir(src, split, j))
            if not written:
                keys = [k for k in sh.arrays if k not in ROAD_KEYS or sh.has_road]
                arrays = fn({k: np.asarray(sh.arrays[k]) for k in keys}, split, j)
                meta = dict(sh.meta)
                ids = [f"{s}{suffix}" for s in meta.get("scenario_ids", [])]
                locations = [f"{loc}{suffix}" for loc in meta.get("locations", [])]
                extra = {k: v for k, v in meta.items()
                         if k not in ("format_version", "num_samples", "keys", "scenario_ids", "locations")}
                extra.update(meta_fn(meta))
                extra[f"{made}_from"] = os.path.join(os.path.abspath(src), split, store.shard_name(j))
                store.write_shard(dst, split, j, arrays, ids, locations, extra=extra)
            if keep_tokens and sh.map_tokens is not None and store.Shard(out).map_tokens is None:
                rec = store.map_tokens_record(src, split, j) or {}
                store.save_map_tokens(dst, split, j, np.asarray(sh.map_tokens), rec.get("tokenizer"),
                                      rec.get("frame_stride", 1))


def mirror_store(src: str, dst: str, splits: list[str] | None = None) -> dict:
    """Writes the mirror image of every shard of `splits` (default: all) of store `src` into store `dst`, with
    the same shard indices; scenario ids get "/mirror" appended and the `lefthand` flag of each shard flips.
    Returns dst's manifest. Raises DataError for an unreadable source shard or when src and dst are the same."""
    _transform_store(src, dst, splits, lambda arrays, split, j: mirror_arrays(arrays), SUFFIX,
                     lambda meta: {"lefthand": not bool(meta.get("lefthand", False))}, "mirrored", keep_tokens=False)
    return store.write_manifest(dst, extra={"mirrored_from": os.path.abspath(src)})


@dataclasses.dataclass(frozen=True)
class SensorView:
    """How an on-board tracker sees the agents other than the ego (slot 0). Defaults: a tracker of a few tenths of
    a metre and a couple of degrees, a lidar's 50 m, a lost track about every 20 s for half a second.

    position_sigma_m: standard deviation of each agent's position error, which drifts slowly: AR(1) with
      `correlation` per stored frame (0.95 at 10 Hz: about 2 s to forget), so speeds stay plausible.
    heading_sigma_deg: the same for its heading.
    range_m: agents farther than this from the ego at a frame are not seen there.
    gap_rate: the chance per agent and stored frame that its track is lost for `gap_frames` frames.
    seed: the noise of shard j of split s comes from `numpy.random.default_rng([seed, zlib.crc32(s), j])`.
    """

    position_sigma_m: float = 0.25
    heading_sigma_deg: float = 2.0
    correlation: float = 0.95
    range_m: float = 50.0
    gap_rate: float = 0.01
    gap_frames: int = 5
    seed: int = 0

    def __post_init__(self):
        for name in ("position_sigma_m", "heading_sigma_deg", "range_m", "gap_rate"):
            if not getattr(self, name) >= 0:
                raise ValueError(f"SensorView.{name} must be >= 0, got {getattr(self, name)}")
        if not 0 <= self.correlation < 1:
            raise ValueError(f"SensorView.correlation must be in [0, 1), got {self.correlation}")
        if self.gap_rate > 1 or self.gap_frames < 1:
            raise ValueError(f"SensorView.gap_rate must be <= 1 and gap_frames >= 1, got {self.gap_rate}, "
                             f"{self.gap_frames}")


def _drift(rng: np.random.Generator, shape: tuple[int, ...], sigma: float, rho: float) -> np.ndarray:
    """f32[n, T, ...] stationary AR(1) noise along axis 1 with standard deviation `sigma` and correlation `rho`."""
    out = np.empty(shape, np.float32)
    out[:, 0] = rng.normal(size=(shape[0],) + shape[2:]) * sigma
    step = rng.normal(size=shape) * sigma * np.sqrt(1.0 - rho ** 2)
    for t in range(1, shape[1]):
        out[:, t] = rho * out[:, t - 1] + step[:, t]
    return out


def sensor_arrays(arrays: dict[str, np.ndarray], view: SensorView, rng: np.random.Generator
                  ) -> dict[str, np.ndarray]:
    """A shard's arrays (xy f32[n, T, A, 2], heading f32[n, T, A], valid bool[n, T, A], ego_pose f32[n, T, 3], ...)
    as `view` sees them: slots >= 1 get the drifting errors where they are seen, and are invalid beyond the range
    and in the gaps; slot 0 and every other key are copied unchanged."""
    out = {k: np.array(v, copy=True) for k, v in arrays.items()}
    xy, heading, valid = out["xy"], out["heading"], out["valid"]
    n, t, a = valid.shape
    seen = np.linalg.norm(xy - out["ego_pose"][:, :, None, :2], axis=-1) <= view.range_m
    start = rng.random((n, t, a)) < view.gap_rate
    lost = np.zeros_like(start)
    for k in range(view.gap_frames):
        lost[:, k:] |= start[:, :t - k]
    keep = seen & ~lost
    keep[:, :, 0] = True
    valid &= keep
    others = valid.copy()
    others[:, :, 0] = False
    dxy = _drift(rng, (n, t, a, 2), view.position_sigma_m, view.correlation)
    dh = _drift(rng, (n, t, a), np.deg2rad(view.heading_sigma_deg), view.correlation)
    xy += np.where(others[..., None], dxy, 0.0).astype(xy.dtype)
    out["heading"] = _wrap(heading + np.where(others, dh, 0.0).astype(heading.dtype))
    return out


def sensor_store(src: str, dst: str, view: SensorView = SensorView(), splits: list[str] | None = None) -> dict:
    """Writes every shard of `splits` (default: all) of store `src`, as `view` sees it (`sensor_arrays`), into
    store `dst` with the same shard indices and the source's map tokens; scenario ids get "/sensor" appended and
    each shard's meta records the view. Deterministic for a given view; a rerun resumes. Returns dst's manifest.
    Raises DataError for an unreadable source shard or when src and dst are the same."""
    record = dataclasses.asdict(view)

    def fn(arrays, split, j):
        return sensor_arrays(arrays, view, np.random.default_rng([view.seed, zlib.crc32(split.encode()), j]))

    _transform_store(src, dst, splits, fn, "/sensor", lambda meta: {"sensor_view": record}, "sensor",
                     keep_tokens=True)
    return store.write_manifest(dst, extra={"sensor_from": os.path.abspath(src), "sensor_view": record})
