"""Store-level augmentation: the mirror image of every scene of a store.

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
"""

from __future__ import annotations

import os

import numpy as np

from gpd_jax.data import store
from gpd_jax.data.errors import DataError
from gpd_jax.data.roadgeom import ROAD_KEYS

POINT_KEYS = ("xy", "polylines", "road_polygons", "road_edges")  # f32[..., 2] points in the scene frame
SUFFIX = "/mirror"


def _wrap(a: np.ndarray) -> np.ndarray:
    return ((a + np.pi) % (2 * np.pi) - np.pi).astype(a.dtype)


def mirror_arrays(arrays: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The mirror image (y -> -y, heading -> -heading) of a shard's (or a sample's) arrays; keys it does not know
    are copied unchanged."""
    out = {k: np.array(v, copy=True) for k, v in arrays.items()}
    for k in POINT_KEYS:
        if k in out:
            out[k][..., 1] *= -1
    if "heading" in out:
        out["heading"] = _wrap(-out["heading"])
    if "ego_pose" in out:
        out["ego_pose"][..., 1] *= -1
        out["ego_pose"][..., 2] = _wrap(-out["ego_pose"][..., 2])
    return out


def mirror_store(src: str, dst: str, splits: list[str] | None = None) -> dict:
    """Writes the mirror image of every shard of `splits` (default: all) of store `src` into store `dst`, with
    the same shard indices; scenario ids get "/mirror" appended and the `lefthand` flag of each shard flips.
    Returns dst's manifest. Raises DataError for an unreadable source shard or when src and dst are the same."""
    if os.path.abspath(src) == os.path.abspath(dst):
        raise DataError(dst, "the mirrored store must be a new directory, not the source")
    splits = splits or store.list_splits(src)
    for split in splits:
        indices = store.shard_indices(src, split)
        if not indices:
            raise DataError(os.path.join(src, split), "no complete shards to mirror")
        for j in indices:
            if os.path.isdir(store.shard_dir(dst, split, j)):
                continue  # written by an earlier run
            sh = store.Shard(store.shard_dir(src, split, j))
            keys = [k for k in sh.arrays if k not in ROAD_KEYS or sh.has_road]
            arrays = mirror_arrays({k: np.asarray(sh.arrays[k]) for k in keys})
            meta = dict(sh.meta)
            ids = [f"{s}{SUFFIX}" for s in meta.get("scenario_ids", [])]
            locations = [f"{loc}{SUFFIX}" for loc in meta.get("locations", [])]
            extra = {k: v for k, v in meta.items()
                     if k not in ("format_version", "num_samples", "keys", "scenario_ids", "locations")}
            extra["lefthand"] = not bool(meta.get("lefthand", False))
            extra["mirrored_from"] = os.path.join(os.path.abspath(src), split, store.shard_name(j))
            store.write_shard(dst, split, j, arrays, ids, locations, extra=extra)
    return store.write_manifest(dst, extra={"mirrored_from": os.path.abspath(src)})
