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
    processes = int(config.data.processes)
    if processes > 0 and repeat and not all_frames and data_dir != "synthetic":
        return _process_batches(config, split, batch_size, seed, shuffle, max_batches, data_dir, processes)
    if data_dir == "synthetic":
        return _prefetch(_synthetic(split, batch_size, seed, repeat, max_batches))
    from gpd_jax.map_tokenizer import store  # the data-store adapter (needs gpd_jax.data)
    return _prefetch(store.frame_batches(data_dir, split, batch_size, seed=seed, shuffle=shuffle,
                                         repeat=repeat, max_batches=max_batches, all_frames=all_frames,
                                         gt_recut=config.data.gt_recut or None),
                     size=max(2, int(config.data.num_workers) + 1))


# ------------------------------------------------------------------------------------------ loader processes
# Building a frame (cropping a network's lanes, resampling them into vector lanes) is many small numpy calls that
# hold the GIL, so threads do not speed it up: one loader thread gives ~400 frames/s, which starves an accelerator.
# With `data.processes = N` the training stream comes from N worker processes, each walking the same data with
# its own seed (`seed * 1009 + k + 1` for worker k), and batches are taken from the workers in turn, so the stream
# is deterministic for a given N. Evaluation (finite passes) keeps the single-process path and its frame order.

def _worker(config, split, batch_size, seed, shuffle, data_dir, out, stop, parent: int) -> None:
    import os

    from gpd_jax.map_tokenizer import store
    try:
        it = store.frame_batches(data_dir, split, batch_size, seed=seed, shuffle=shuffle, repeat=True,
                                 gt_recut=config.data.gt_recut or None)
        for batch in it:
            while not stop.is_set() and os.getppid() == parent:  # the consumer stopped, or was killed
                try:
                    out.put(batch, timeout=0.5)
                    break
                except queue.Full:
                    continue
            if stop.is_set() or os.getppid() != parent:
                return
    except BaseException as e:  # surfaced in the consumer
        out.put(RuntimeError(f"map-tokenizer loader process (seed {seed}) failed: {type(e).__name__}: {e}"))


def _process_batches(config, split, batch_size, seed, shuffle, max_batches, data_dir, processes):
    import multiprocessing as mp
    import os

    ctx = mp.get_context("spawn")  # never fork a process that has started JAX's threads
    stop = ctx.Event()
    queues, procs = [], []
    saved = os.environ.get("JAX_PLATFORMS")
    os.environ["JAX_PLATFORMS"] = "cpu"  # the workers only run numpy; keep them off the accelerator
    try:
        for k in range(processes):
            q = ctx.Queue(maxsize=4)
            p = ctx.Process(target=_worker, args=(config, split, batch_size, seed * 1009 + k + 1, shuffle, data_dir,
                                                  q, stop, os.getpid()), daemon=True)
            p.start()
            queues.append(q)
            procs.append(p)
    finally:
        if saved is None:
            os.environ.pop("JAX_PLATFORMS", None)
        else:
            os.environ["JAX_PLATFORMS"] = saved

    def gen():
        try:
            i = 0
            while max_batches is None or i < max_batches:
                k = i % processes
                while True:
                    try:
                        item = queues[k].get(timeout=5.0)
                        break
                    except queue.Empty:
                        if not procs[k].is_alive():
                            raise RuntimeError(f"map-tokenizer loader process {k} exited "
                                               f"(exit code {procs[k].exitcode})") from None
                if isinstance(item, BaseException):
                    raise item
                yield item
                i += 1
        finally:
            stop.set()
            for p in procs:
                p.join(timeout=2.0)
                if p.is_alive():
                    p.terminate()

    return gen()
