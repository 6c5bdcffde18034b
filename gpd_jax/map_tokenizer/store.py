"""Frame batches for the map tokenizer from the processed data store (`gpd_jax.data.store`).

Each item is one (sample, frame) pair: the sample's polylines (scene frame) and validity, the frame's ego pose,
and the frame's SLEDGE vector lanes (`gpd_jax.data.lanes.vector_lanes`, the targets of the lane decoder).
Rasterization is left to the consumer (it runs inside the jitted train / eval step).
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

from gpd_jax.data.lanes import RECUT_MODES, vector_lanes
from gpd_jax.data.loader import parse_mixture
from gpd_jax.data.store import Shard, list_shards
from gpd_jax.map_tokenizer.netframes import NetFrames, is_netframes

_KEYS = ("polylines", "polyline_valid", "ego_pose")


def open_split(data_dir: str, split: str) -> list[Shard]:
    shards = [Shard(p) for p in list_shards(data_dir, split)]
    if not shards:
        raise FileNotFoundError(f"{data_dir} has no complete shards in split {split!r}")
    return shards


def _item(shard: Shard, i: int, t: int, gt_recut: str | None = None) -> dict[str, np.ndarray]:
    s = shard.read(i, _KEYS)
    pose = s["ego_pose"][t]
    lanes, ok = vector_lanes(s["polylines"], s["polyline_valid"], pose, recut=gt_recut)
    return dict(polylines=s["polylines"], polyline_valid=s["polyline_valid"], pose=pose.astype(np.float32),
                lanes=lanes.astype(np.float32), lanes_valid=ok, sample=np.int32(i), frame=np.int32(t))


def _stack(items: list[dict]) -> dict[str, np.ndarray]:
    return {k: np.stack([it[k] for it in items]) for k in items[0]}


def frame_batches(data_dir: str, split: str, batch_size: int, seed: int = 0, shuffle: bool = True,
                  repeat: bool = True, max_batches: int | None = None, all_frames: bool = False,
                  frame_stride: int | None = None, gt_recut: str | None = None) -> Iterator[dict[str, np.ndarray]]:
    """Batches of frames (dict of numpy arrays, see `gpd_jax.map_tokenizer.data`).

    One random frame per sample and pass (deterministic in `seed`), or with `frame_stride` the frames
    0, stride, 2 stride, ... of every sample (evaluation), or with `all_frames` every frame. `data_dir` may be a
    weighted mixture of stores `"DIR:0.7,DIR:0.3"` (`gpd_jax.data.loader.parse_mixture`) for training
    (shuffled, repeated, one random frame per sample): each frame comes from a store drawn by weight, and each
    store walks its own permutations (`sample` then indexes that store). A single netframes directory without
    `shuffle` or `repeat` (evaluation) gives the `max_batches` batches its seeded draw makes, the same for every
    caller with the same `seed`. `gt_recut` (a
    `gpd_jax.data.lanes.RECUT_MODES` mode) makes the targets the stored lanes re-cut that way; the polylines (the
    input raster) stay as stored.
    """
    if gt_recut and gt_recut not in RECUT_MODES:
        raise ValueError(f"gt_recut must be one of {RECUT_MODES} or empty, got {gt_recut!r}")
    mixture = parse_mixture(data_dir)
    if len(mixture) == 1 and is_netframes(mixture[0][0]) and not (shuffle and repeat):
        if max_batches is None:
            raise ValueError(f"{data_dir} is a netframes directory: its frames are drawn, so give max_batches to "
                             "evaluate on it")
        yield from _mixture_batches(mixture, split, batch_size, seed, max_batches, gt_recut)
        return
    if len(mixture) > 1 or is_netframes(mixture[0][0]):
        if not (shuffle and repeat) or all_frames or frame_stride:
            raise ValueError(f"a mixture of stores or a netframes directory ({data_dir}) is for training batches (shuffled, repeated, one "
                             "random frame per sample); evaluate one store at a time")
        yield from _mixture_batches(mixture, split, batch_size, seed, max_batches, gt_recut)
        return
    data_dir = mixture[0][0]
    shards = open_split(data_dir, split)
    index = [(s, i) for s in range(len(shards)) for i in range(shards[s].num_samples)]
    num_frames = shards[0].arrays["ego_pose"].shape[1]
    frames = range(0, num_frames, 1 if all_frames else frame_stride) if (all_frames or frame_stride) else None
    per_pass = len(index) * (len(frames) if frames else 1)
    if repeat and per_pass < batch_size:  # every pass would end before a full batch: it would never yield
        raise ValueError(f"{data_dir} split {split!r} gives {per_pass} frames per pass, fewer than a batch of "
                         f"{batch_size}: lower the batch size or add samples")
    rng = np.random.default_rng(seed)
    made = 0
    while True:
        order = rng.permutation(len(index)) if shuffle else np.arange(len(index))
        pairs = []
        for j in order:
            s, i = index[j]
            if frames:
                pairs.extend((s, i, t) for t in frames)
            else:
                pairs.append((s, i, int(rng.integers(num_frames))))
        for k in range(0, len(pairs), batch_size):
            if max_batches is not None and made >= max_batches:
                return
            chunk = pairs[k:k + batch_size]
            if repeat and len(chunk) < batch_size:
                break  # keep shapes fixed while training
            yield _stack([_item(shards[s], i, t, gt_recut) for s, i, t in chunk])
            made += 1
        if not repeat:
            return


def _mixture_batches(mixture, split: str, batch_size: int, seed: int,
                     max_batches: int | None, gt_recut: str | None = None) -> Iterator[dict[str, np.ndarray]]:
    """Endless training batches from a mixture of stores and netframes directories (`netframes`; `split` does
    not apply to them) (see `frame_batches`), deterministic in `seed`."""
    weights = np.asarray([w for _, w in mixture], np.float64)
    pick = np.random.default_rng((seed, len(mixture)))

    def walk(k: int, d: str) -> Iterator[dict[str, np.ndarray]]:
        if is_netframes(d):
            yield from NetFrames(d).walk(seed + 1000 * k, gt_recut=gt_recut)
            return
        shards = open_split(d, split)
        rng = np.random.default_rng((seed, k))
        index = [(s, i) for s in range(len(shards)) for i in range(shards[s].num_samples)]
        num_frames = shards[0].arrays["ego_pose"].shape[1]
        while True:
            for j in rng.permutation(len(index)):
                s, i = index[j]
                yield _item(shards[s], i, int(rng.integers(num_frames)), gt_recut)

    walks = [walk(k, d) for k, (d, _) in enumerate(mixture)]
    made = 0
    while max_batches is None or made < max_batches:
        yield _stack([next(walks[k]) for k in pick.choice(len(walks), size=batch_size, p=weights)])
        made += 1
