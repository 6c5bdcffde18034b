"""Batches of single frames for the map tokenizer: polylines + ego pose (to rasterize) and vector-lane targets.

A batch is a dict of numpy arrays with a leading batch dim B:
  polylines f32[B, L, P, 2] (scene frame), polyline_valid bool[B, L, P], pose f32[B, 3] (the frame's ego pose),
  lanes f32[B, 50, 20, 2] (SLEDGE vector lanes in the frame's ego frame), lanes_valid bool[B, 50],
  plus `sample` i32[B] and `frame` i32[B] saying where each came from.

`config.data.dir == "synthetic"` gives hand-built maps (`synthetic.py`, tests only); otherwise frames come from
the processed data store (`gpd_jax.data`), one random frame per sample during training. `config.data.gt_recut`
(a `gpd_jax.data.lanes.RECUT_MODES` mode, "" for none) trains and validates on the lanes re-cut that way.
"""

from __future__ import annotations

import queue
import threading
from typing import Iterator

from gpd_jax.map_tokenizer.synthetic import synthetic_lanes


def _prefetch(gen: Iterator[dict], size: int = 2) -> Iterator[dict]:
    """Runs `gen` in a background thread, `size` batches ahead."""
    q: queue.Queue = queue.Queue(maxsize=size)
    done = object()

    def work():
        try:
            for item in gen:
                q.put(item)
        except BaseException as e:  # surfaced in the consumer
            q.put(e)
        q.put(done)

    threading.Thread(target=work, daemon=True).start()
    while True:
        item = q.get()
        if item is done:
            return
        if isinstance(item, BaseException):
            raise item
        yield item


def _synthetic(split: str, batch_size: int, seed: int, repeat: bool, max_batches: int | None):
    base = {"train": 0, "val": 1_000_000, "test": 2_000_000}.get(split, 3_000_000)
    i = 0
    while max_batches is None or i < max_batches:
        if not repeat and i >= 64:
            return
        yield synthetic_lanes(base + seed * 10_007 + i, batch_size)
        i += 1


def frame_batches(config, split: str, batch_size: int, seed: int = 0, shuffle: bool = True, repeat: bool = True,
                  max_batches: int | None = None, all_frames: bool = False,
                  data_dir: str | None = None) -> Iterator[dict]:
    """Iterator of frame batches (see the module docstring).

    Args:
      config: a map-tokenizer config (uses `config.data`).
      data_dir: read this store instead of `config.data.dir` (one store or a training mixture
        `"DIR:0.7,DIR:0.3"`).
      split: data split name ("train", "val", "test").
      batch_size: frames per batch (the last batch of a finite pass may be smaller).
      seed: shuffling / frame-choice seed (deterministic).
      shuffle: shuffle samples.
      repeat: cycle forever (training) or make one pass.
      max_batches: stop after this many batches.
      all_frames: every frame of every sample in order (token extraction) instead of one random frame per sample.
    """
    data_dir = config.data.dir if data_dir is None else data_dir
    if data_dir == "synthetic":
        return _prefetch(_synthetic(split, batch_size, seed, repeat, max_batches))
    from gpd_jax.map_tokenizer import store  # the data-store adapter (needs gpd_jax.data)
    return _prefetch(store.frame_batches(data_dir, split, batch_size, seed=seed, shuffle=shuffle,
                                         repeat=repeat, max_batches=max_batches, all_frames=all_frames,
                                         gt_recut=config.data.get("gt_recut") or None),
                     size=max(2, int(config.data.num_workers) + 1))
