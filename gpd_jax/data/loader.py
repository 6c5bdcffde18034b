"""Loading samples as `gpd_jax.scene.Scene` batches (numpy arrays, batch dim leading).

Two APIs:

* `make_loader(data_dir, split, batch_size, seed, ...)`: a grain pipeline. Records are shuffled
  deterministically by `seed` (a fresh permutation per epoch), optionally sharded across processes
  (`process_blocks`: process p reads rows p*b .. (p+1)*b - 1 of every global batch of P*b samples, so the P
  processes together read exactly the batches of one process with batch P*b, in the same order), batched,
  read by a thread pool and prefetched in a background thread. Everything is a pure function of
  (seed, step): `start_step=k` yields exactly the batches a fresh loader yields from its k-th on, which is
  how training resumes after a restart. Memory stays flat: shards are memory-mapped and at most
  `max_open_shards` are open at a time; only the prefetch buffer holds batches.
* `load_split(data_dir, split)`: a whole (small) split as one stacked Scene, for evaluation.

`make_loader` also reads a *mixture* of stores: `data_dir` = `"DIR_A:0.7,DIR_B:0.3"` (`parse_mixture`) draws
every sample from store A with probability 0.7 and from B with 0.3, each store shuffled by its own seed and
repeated on its own (so a small store is seen more often than its share of the scenes), still a pure function
of (seed, step) and resumable with `start_step`. A single directory reads exactly as before.

Map tokens written by the tokenizer (`store.save_map_tokens`) fill `Scene.map_tokens` with `map_valid`
True; without them, and in frames that were not encoded (`encode --frame-stride`), tokens are 0 and
`map_valid` False. With `with_lanes=True` the SLEDGE vector lanes
of every frame (`gpd_jax.data.lanes`) fill `Scene.lanes` / `lanes_valid` (computed on the fly, ~10-20 ms
per sample). With `with_polylines=True` each batch comes as `(scene, polylines)` where
`polylines = {"polylines": f32[B, L, P, 2], "polyline_valid": bool[B, L, P]}`, the stored lane centrelines
in the scene frame; the frame poses are `scene.ego_pose` (what the rasterizer takes). With the polylines, the
road geometry (`store.ROAD_KEYS`) is read too where every shard of the split has it, and `to_scene` makes
`Scene.road` (else None: a store built before it; rebuild to get it).
"""

from __future__ import annotations

import atexit
import collections
import os
import threading
import weakref
from typing import Any, Iterator

import numpy as np

from gpd_jax.data import lanes as lanes_lib
from gpd_jax.data import store
from gpd_jax.data.errors import DataError
from gpd_jax.data.roadgeom import MAP_EDGE_KEYS, ROAD_KEYS
from gpd_jax.data.signals import SIGNAL_KEYS
from gpd_jax.geometry import TrafficSignals, road_from_arrays
from gpd_jax.scene import Scene

SCENE_KEYS = ("xy", "heading", "valid", "size", "agent_type", "ego_pose")
POLY_KEYS = ("polylines", "polyline_valid")


class SplitSource:
    """Random access to every sample of a split (grain `RandomAccessDataSource` protocol).

    Item i is a dict of numpy arrays: the `SCENE_KEYS`, `map_tokens` i32[T, 64], `map_valid` bool[T], and
    the `POLY_KEYS` if `with_polylines`. Raises `DataError` naming the file for corrupt or truncated shards
    and for non-finite values.
    """

    def __init__(self, data_dir: str, split: str, with_polylines: bool = False, max_open_shards: int = 32):
        self.data_dir, self.split = data_dir, split
        self.paths = store.list_shards(data_dir, split)
        if not self.paths:
            raise DataError(os.path.join(data_dir, split), "no complete shards in this split")
        counts, road, edges, signals = [], [], [], []
        for p in self.paths:
            n, has = _read_count(p)
            counts.append(n)
            road.append(has["road"])
            edges.append(has["map_edges"])
            signals.append(has["signals"])
        self.counts = np.asarray(counts, np.int64)
        self.offsets = np.concatenate([[0], np.cumsum(self.counts)])
        # the road geometry comes with the polylines (its lane centrelines), where every shard has it; so do the
        # map edges and the signals (stores of format 1 have neither: their scenes read as before)
        self.has_road = all(road)
        self.has_map_edges = self.has_road and all(edges)
        self.has_signals = all(signals)
        extra = ((ROAD_KEYS if self.has_road else ()) + (MAP_EDGE_KEYS if self.has_map_edges else ())
                 + (SIGNAL_KEYS if self.has_signals else ()))
        self.keys = SCENE_KEYS + (POLY_KEYS + extra if with_polylines else ())
        self.max_open = max_open_shards
        self._open: collections.OrderedDict[int, store.Shard] = collections.OrderedDict()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        return int(self.offsets[-1])

    def _shard(self, s: int) -> store.Shard:
        with self._lock:
            sh = self._open.get(s)
            if sh is not None:
                self._open.move_to_end(s)
                return sh
        sh = store.Shard(self.paths[s])
        if sh.num_samples != self.counts[s]:
            raise DataError(self.paths[s], "shard changed while reading")
        with self._lock:
            self._open[s] = sh
            while len(self._open) > self.max_open:
                self._open.popitem(last=False)
        return sh

    def locate(self, i: int) -> tuple[int, int]:
        if not 0 <= i < len(self):
            raise IndexError(i)
        s = int(np.searchsorted(self.offsets, i, side="right") - 1)
        return s, int(i - self.offsets[s])

    def __getitem__(self, i: int) -> dict[str, np.ndarray]:
        s, j = self.locate(int(i))
        sh = self._shard(s)
        out = sh.read(j, self.keys)
        T = out["xy"].shape[0]
        if sh.map_tokens is not None:
            tokens = np.asarray(sh.map_tokens[j], np.int32)
            out["map_valid"] = ~(tokens == store.MISSING_MAP_TOKEN).all(-1)
            out["map_tokens"] = np.where(out["map_valid"][:, None], tokens, 0)
        else:
            out["map_tokens"] = np.zeros((T, store.NUM_MAP_TOKENS), np.int32)
            out["map_valid"] = np.zeros((T,), bool)
        return out

    def __repr__(self) -> str:
        return f"SplitSource({self.data_dir!r}, {self.split!r}, {len(self)} samples)"


def _read_count(path: str) -> tuple[int, dict[str, bool]]:
    """(sample count, {"road", "map_edges", "signals": whether the shard has those keys}) from its meta.json."""
    import json

    mp = os.path.join(path, "meta.json")
    try:
        with open(mp) as f:
            meta = json.load(f)
        keys = meta.get("keys", {})
        has = {name: all(k in keys for k in group)
               for name, group in (("road", ROAD_KEYS), ("map_edges", MAP_EDGE_KEYS), ("signals", SIGNAL_KEYS))}
        return int(meta["num_samples"]), has
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise DataError(mp, f"unreadable shard metadata: {e}") from e


def add_lanes(rec: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Adds SLEDGE vector lanes (`lanes` f32[T, 50, 20, 2], `lanes_valid` bool[T, 50]) to a record."""
    if "polylines" not in rec:
        raise KeyError("add_lanes needs the polylines (with_polylines=True)")
    lanes, ok = lanes_lib.vector_lanes_frames(rec["polylines"], rec["polyline_valid"], rec["ego_pose"])
    return {**rec, "lanes": lanes, "lanes_valid": ok}


def to_scene(batch: dict[str, np.ndarray]) -> Scene:
    """A dict of (batched) record arrays -> Scene (numpy leaves, agent_type as int32); with the road keys and the
    polylines, `Scene.road` is their `RoadGeometry` (lane centrelines = the polylines; map edges where the batch
    has them), else None; with the signal keys, `Scene.signals` is their `TrafficSignals`, else None."""
    road = signals = None
    if all(k in batch for k in ROAD_KEYS) and "polylines" in batch:
        road = road_from_arrays(batch, batch["polylines"], batch["polyline_valid"])
        road = road.replace(polygon_kind=road.polygon_kind.astype(np.int32))
    if all(k in batch for k in SIGNAL_KEYS):
        signals = TrafficSignals(state=batch["signal_state"].astype(np.int32), stop=batch["signal_stop"],
                                 lane=batch["signal_lane"], lane_valid=batch["signal_lane_valid"])
    return Scene(xy=batch["xy"], heading=batch["heading"], valid=batch["valid"], size=batch["size"],
                 agent_type=batch["agent_type"].astype(np.int32), map_tokens=batch["map_tokens"],
                 map_valid=batch["map_valid"], ego_pose=batch["ego_pose"], lanes=batch.get("lanes"),
                 lanes_valid=batch.get("lanes_valid"), polylines=batch.get("polylines"),
                 polyline_valid=batch.get("polyline_valid"), road=road, signals=signals)


def _split_output(with_polylines: bool):
    def fn(batch):
        scene = to_scene(batch)
        if with_polylines:
            return scene, {k: batch[k] for k in POLY_KEYS}
        return scene
    return fn


def parse_mixture(spec: str) -> tuple[tuple[str, float], ...]:
    """`"DIR"` or `"DIR:WEIGHT,DIR:WEIGHT,..."` -> ((dir, weight), ...), the weights normalised to sum to 1 (a
    directory given without a weight weighs 1; text after the last colon that is not a number belongs to the
    directory's name). Raises `DataError` naming the spec for an empty entry, a weight that is not positive and
    finite, or a directory named twice."""
    import math

    if not spec or not spec.strip():
        raise DataError("data_dir", "no data directory given")
    out: list[tuple[str, float]] = []
    for part in spec.split(","):
        part = part.strip()
        d, sep, w = part.rpartition(":")
        try:
            weight = float(w) if sep else 1.0
        except ValueError:  # a colon inside the directory's name, no weight
            d, weight = part, 1.0
        if not sep:
            d = part
        if not d:
            raise DataError(spec, f"mixture entry {part!r} has no directory (format DIR:WEIGHT,DIR:WEIGHT)")
        if not (math.isfinite(weight) and weight > 0):
            raise DataError(spec, f"mixture entry {part!r}: the weight must be positive and finite")
        out.append((d, weight))
    names = [os.path.normpath(d) for d, _ in out]
    if len(set(names)) != len(names):
        raise DataError(spec, "a directory is named twice in the mixture")
    total = sum(w for _, w in out)
    return tuple((d, w / total) for d, w in out)


def process_blocks(ds, block: int, index: int, count: int):
    """Process `index`'s share of the sample order `ds` (a grain MapDataset) when `count` processes each read
    `block` samples of every global batch of `count * block`: element i is `ds[(i // block * count + index) *
    block + i % block]`. Batched by `block`, process p's batch k is rows p*block .. (p+1)*block - 1 of global
    batch k; laid out over the processes' devices in process order, the global batch is the one a single process
    reads with batch `count * block`."""
    import grain

    n = len(ds) // (block * count) * block

    def read(i):
        q, r = divmod(int(i), block)
        return ds[(q * count + index) * block + r]

    return grain.MapDataset.range(n).map(read)


def make_dataset(data_dir: str, split: str, batch_size: int, seed: int = 0, *, shuffle: bool = True,
                 num_epochs: int | None = None, drop_remainder: bool = True, process_index: int = 0,
                 process_count: int = 1, start_step: int = 0, with_polylines: bool = False,
                 with_lanes: bool = False):
    """The grain `MapDataset` of batches (before threading/prefetch): indexable, `len` = number of batches
    (huge when `num_epochs` is None). Element k is batch k of this process. `data_dir` may be a mixture
    (`parse_mixture`; endless, so `num_epochs` must be None)."""
    import grain

    if not 0 <= process_index < process_count:
        raise ValueError(f"process_index {process_index} not in [0, {process_count})")
    mixture = parse_mixture(data_dir)
    if len(mixture) > 1 and num_epochs is not None:
        raise ValueError(f"a mixture of stores ({data_dir}) is endless: num_epochs must be None")
    parts, roads = [], {}
    for i, (d, _) in enumerate(mixture):
        src = SplitSource(d, split, with_polylines=with_polylines or with_lanes)
        roads[d] = src.has_road
        part = grain.MapDataset.source(src)
        if shuffle:
            part = part.shuffle(seed=seed + i)
        parts.append(part.repeat(num_epochs))
    if len(parts) > 1:
        if (with_polylines or with_lanes) and len(set(roads.values())) > 1:
            raise DataError(data_dir, f"only some stores of the mixture have road geometry ({roads}); "
                            "rebuild the others or read without polylines")
        ds = grain.MapDataset.mix(parts, [w for _, w in mixture])
    else:
        ds = parts[0]
    if process_count > 1:
        ds = process_blocks(ds, batch_size, process_index, process_count)
    if with_lanes:
        ds = ds.map(add_lanes)
    ds = ds.batch(batch_size, drop_remainder=drop_remainder)
    if start_step:
        ds = ds[start_step:]
    return ds


def make_loader(data_dir: str, split: str, batch_size: int, seed: int = 0, *, shuffle: bool = True,
                num_epochs: int | None = None, drop_remainder: bool = True, process_index: int = 0,
                process_count: int = 1, start_step: int = 0, with_polylines: bool = False,
                with_lanes: bool = False, num_threads: int = 4, prefetch: int = 4) -> Iterator[Any]:
    """Iterator of `Scene` batches (or `(Scene, polylines)` with `with_polylines`), see the module doc.

    Args:
      data_dir: a store, or a mixture of stores `"DIR:WEIGHT,DIR:WEIGHT"` (`parse_mixture`).
      seed: shuffling seed (same seed, same order; each epoch is a new permutation).
      num_epochs: None repeats forever.
      process_index, process_count: this process's share of every epoch (e.g. `jax.process_index()`).
      start_step: skip this many batches of this process exactly (resume after a restart).
      num_threads: reader threads; prefetch: batches buffered by the background thread.
    """
    import grain

    ds = make_dataset(data_dir, split, batch_size, seed, shuffle=shuffle, num_epochs=num_epochs,
                      drop_remainder=drop_remainder, process_index=process_index, process_count=process_count,
                      start_step=start_step, with_polylines=with_polylines, with_lanes=with_lanes)
    it = ds.to_iter_dataset(grain.ReadOptions(num_threads=num_threads, prefetch_buffer_size=max(1, prefetch)
                                              * batch_size))
    it = it.map(_split_output(with_polylines))
    if prefetch > 0:
        it = grain.experimental.ThreadPrefetchIterDataset(it, prefetch_buffer_size=prefetch)
    return _Iterator(iter(it))


class _Iterator:
    """The loader's iterator: forwards to grain's, and releases it at interpreter exit (grain's prefetch
    iterators stop their threads in `__del__`, which fails noisily during interpreter teardown)."""

    def __init__(self, it):
        self._it = it
        _LIVE.add(self)

    def __iter__(self):
        return self

    def __next__(self):
        return next(self._it)

    def close(self) -> None:
        if self._it is not None:
            it, self._it = self._it, None
            close = getattr(it, "close", None)
            if close is not None:
                close()


_LIVE: "weakref.WeakSet" = weakref.WeakSet()


@atexit.register
def _close_live_iterators():
    for it in list(_LIVE):
        try:
            it.close()
        except Exception:  # noqa: BLE001 - best effort at exit
            pass


def load_split(data_dir: str, split: str, *, with_polylines: bool = False, with_lanes: bool = False,
               indices=None):
    """A whole split (or `indices` of it) as one Scene with leading dim n (for small evaluation sets).

    Returns `Scene`, or `(Scene, polylines dict)` with `with_polylines`.
    """
    src = SplitSource(data_dir, split, with_polylines=with_polylines or with_lanes)
    idx = range(len(src)) if indices is None else indices
    recs = [src[int(i)] for i in idx]
    if with_lanes:
        recs = [add_lanes(r) for r in recs]
    batch = {k: np.stack([r[k] for r in recs]) for k in recs[0]}
    return _split_output(with_polylines)(batch)


def benchmark(data_dir: str, split: str = "train", batch_size: int = 32, num_batches: int = 200, seed: int = 0,
              **kw) -> dict:
    """Loader throughput (samples/s after the first batch) and memory (peak RSS and its growth over the run)."""
    import resource
    import time

    def rss_mb():
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20

    it = make_loader(data_dir, split, batch_size, seed, **kw)
    next(it)
    rss0 = rss_mb()
    t0 = time.perf_counter()
    rss_max = rss0
    for k in range(num_batches):
        next(it)
        if k % 10 == 0:
            rss_max = max(rss_max, rss_mb())
    dt = time.perf_counter() - t0
    return {"samples_per_s": num_batches * batch_size / dt, "batch_size": batch_size, "num_batches": num_batches,
            "rss_after_first_batch_mb": rss0, "rss_max_mb": max(rss_max, rss_mb()),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "options": kw}
