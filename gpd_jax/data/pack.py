"""Packing stores to carry them to another machine: one `.tar.xz` per store, holding only what a model reads.

A store is about 190 kB a sample, most of it frames and slots a 1 Hz, 17-slot model never reads, lanes and road
geometry. `pack_store` keeps the splits asked for and, optionally:

- `frame_stride=S`: the stored frames a model at that stride reads, k S, and the frame before each, k S - 1 (its
  stored-rate velocity input, `Scene.subsample(..., velocity_period_s=...)`, and constant velocity's); every other
  frame's xy / heading become 0 and valid False (same shapes, so readers are unchanged; the zeros compress away);
- `num_agents=A`: slots from A on are cleared the same way;
- `drop_road=True`: the five road-geometry keys are left out (training does not read them; the loader then gives
  `Scene.road` None, as for stores built before them).

What was dropped is recorded in the packed store's `dataset.json` ("packed"), and `check_packed` (called by
training and evaluation) refuses a model that would read a cleared frame or slot, naming both strides. A model's
view of a packed sample (`ModelSpec.view`) is identical to its view of the original (tests/test_data_pack.py).

    python -m gpd_jax.data pack data/legacy_train data/real2_train --out packs --frame-stride 10 --agents 17 \
        --drop-road                             # -> packs/legacy_train.tar.xz, packs/real2_train.tar.xz
    tar xf packs/legacy_train.tar.xz -C data    # on the other machine: data/legacy_train, a store

Archives are written to a temporary file and renamed; one that exists is kept (a stopped run resumes).
"""

from __future__ import annotations

import io
import json
import os
import tarfile
from collections.abc import Callable, Sequence

import numpy as np

from gpd_jax.data.errors import DataError
from gpd_jax.data.roadgeom import MAP_EDGE_KEYS, ROAD_KEYS
from gpd_jax.data.store import MANIFEST, list_shards, list_splits, read_manifest
from gpd_jax.fsutil import atomic_path

PACKED = "packed"  # the manifest's record of what a pack left out
_FRAME_KEYS = ("xy", "heading", "valid")  # [n, T, A, ...] arrays cleared outside the kept frames and slots


def kept_frames(num_frames: int, frame_stride: int | None) -> np.ndarray:
    """bool[num_frames]: the stored frames a model at `frame_stride` reads (k S and k S - 1); all without one."""
    keep = np.zeros(num_frames, bool)
    if not frame_stride:
        keep[:] = True
        return keep
    keep[::frame_stride] = True
    keep[frame_stride - 1::frame_stride] = True
    return keep


def _clear(a: np.ndarray, frames: np.ndarray, num_agents: int | None) -> np.ndarray:
    a = np.array(a)
    a[:, ~frames] = 0
    if num_agents is not None:
        a[:, :, num_agents:] = 0
    return a


def _add_bytes(tf: tarfile.TarFile, arcname: str, data: bytes) -> None:
    info = tarfile.TarInfo(arcname)
    info.size = len(data)
    info.mode = 0o644
    tf.addfile(info, io.BytesIO(data))


def pack_store(data_dir: str, out_dir: str, *, splits: Sequence[str] = ("train",), frame_stride: int | None = None,
               num_agents: int | None = None, drop_road: bool = False, preset: int = 6,
               log: Callable[[str], None] = print) -> str:
    """Writes `out_dir/<store name>.tar.xz` (members under `<store name>/`) and returns its path; an archive that
    exists is kept. Raises DataError naming the store on bad input (no manifest, a split it lacks, a stride or slot
    count below 1, or a store that is itself a pack: pack its source instead)."""
    data_dir = os.path.normpath(data_dir)
    name = os.path.basename(data_dir)
    manifest = read_manifest(data_dir)
    have = list_splits(data_dir)
    missing = [s for s in splits if s not in have]
    if not splits or missing:
        raise DataError(data_dir, f"no split {', '.join(map(repr, missing)) or '(none asked)'} to pack "
                                  f"(splits: {', '.join(have) or 'none'})")
    if frame_stride is not None and frame_stride < 1:
        raise DataError(data_dir, f"frame_stride must be >= 1, got {frame_stride}")
    if num_agents is not None and num_agents < 1:
        raise DataError(data_dir, f"num_agents must be >= 1, got {num_agents}")
    if manifest.get(PACKED):
        raise DataError(data_dir, f"this store is a pack already; pack its source, {manifest[PACKED].get('source')}")
    path = os.path.join(out_dir, f"{name}.tar.xz")
    if os.path.exists(path):
        log(f"{path} exists; kept (delete it to pack {data_dir} again)")
        return path
    dropped = list(ROAD_KEYS + MAP_EDGE_KEYS) if drop_road else []
    record = {"frame_stride": frame_stride, "num_agents": num_agents,
              "frames_kept": "k * frame_stride and k * frame_stride - 1" if frame_stride else "all",
              "dropped_keys": sorted(dropped), "splits": list(splits), "source": os.path.abspath(data_dir)}
    with atomic_path(path, suffix=".tar.xz") as tmp:
        with tarfile.open(tmp, "w:xz", preset=preset) as tf:
            m = dict(manifest)
            m["splits"] = {s: v for s, v in manifest.get("splits", {}).items() if s in splits}
            m["num_samples"] = sum(int(v.get("num_samples", 0)) for v in m["splits"].values())
            m["keys"] = {k: v for k, v in manifest.get("keys", {}).items() if k not in dropped}
            m[PACKED] = record
            _add_bytes(tf, f"{name}/{MANIFEST}", json.dumps(m, indent=1).encode())
            for split in splits:
                for shard in list_shards(data_dir, split):
                    _pack_shard(tf, shard, f"{name}/{split}/{os.path.basename(shard)}", frame_stride, num_agents,
                                dropped)
    raw = sum(os.path.getsize(os.path.join(r, f)) for s in splits for r, _, fs in os.walk(os.path.join(data_dir, s))
              for f in fs)
    log(f"{name}: {', '.join(splits)} -> {path} ({os.path.getsize(path) / 1e6:.1f} MB from {raw / 1e6:.1f} MB)")
    return path


def _pack_shard(tf: tarfile.TarFile, shard: str, arc: str, frame_stride: int | None, num_agents: int | None,
                dropped: Sequence[str]) -> None:
    with open(os.path.join(shard, "meta.json")) as f:
        meta = json.load(f)
    meta["keys"] = {k: v for k, v in meta.get("keys", {}).items() if k not in dropped}
    for fname in sorted(os.listdir(shard)):
        src = os.path.join(shard, fname)
        key = fname[:-4] if fname.endswith(".npy") else None
        if fname == "meta.json" or key in dropped or not os.path.isfile(src):
            continue
        if key in _FRAME_KEYS and (frame_stride or num_agents is not None):
            a = np.load(src, allow_pickle=False)
            a = _clear(a, kept_frames(a.shape[1], frame_stride), num_agents)
            buf = io.BytesIO()
            np.save(buf, a, allow_pickle=False)
            data = buf.getvalue()
            if len(data) != os.path.getsize(src):
                raise DataError(src, "the cleared array's file size differs from the original's (not a plain .npy?)")
            _add_bytes(tf, f"{arc}/{fname}", data)
        else:
            tf.add(src, arcname=f"{arc}/{fname}", recursive=False)
    _add_bytes(tf, f"{arc}/meta.json", json.dumps(meta).encode())


def packed_record(data_dir: str) -> dict | None:
    """The manifest's "packed" record of a packed store, None for any other (or one without a manifest)."""
    try:
        return read_manifest(data_dir).get(PACKED)
    except DataError:
        return None


def check_packed(data_dir: str, frame_stride: int, num_agents: int) -> None:
    """Raises DataError if `data_dir` is a packed store whose cleared frames or slots a model at `frame_stride`
    with `num_agents` slots would read (its stride must be a multiple of the pack's; its slots at most the pack's).
    Nothing for an unpacked store."""
    rec = packed_record(data_dir)
    if not rec:
        return
    s, a = rec.get("frame_stride"), rec.get("num_agents")
    problems = []
    if s and int(frame_stride) % int(s):
        problems.append(f"it keeps the frames of stride {s} (and the one before each), and stride {frame_stride} "
                        "reads others")
    if a is not None and int(num_agents) > int(a):
        problems.append(f"it keeps {a} agent slots, and the model has {num_agents}")
    if problems:
        raise DataError(data_dir, "a packed store (python -m gpd_jax.data pack) this model cannot read: "
                                  + "; ".join(problems) + f"; pack {rec.get('source', 'the original')} again")
