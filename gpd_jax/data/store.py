"""Sharded on-disk store of fixed-shape samples.

Layout of a dataset directory `DIR`::

    DIR/dataset.json                  manifest: format version, sample spec (key -> dtype, shape), splits
                                      (shards, sample counts), build settings and statistics
    DIR/<split>/shard_<jjjjj>/        one complete shard (split = train | val | test | any name)
        meta.json                     {"num_samples": n, "keys": {key: {"dtype", "shape", "nbytes"}},
                                       "scenario_ids": [n strings], "locations": [n strings], ...};
                                      SUMO shards add "layout" (grid | spider | random | real | given) of
                                      their one network: `sample_layouts` lists it per sample
        <key>.npy                     one numpy array per sample key, leading dim n (see below)
        map_tokens.npy                optional, u8[n, T, 64]: written later by `save_map_tokens`; frames that
                                      were not encoded (`encode --frame-stride S`) hold MISSING_MAP_TOKEN
        map_tokens.json               optional: {"tokenizer", "shape", "frame_stride"} of map_tokens.npy
    DIR/_jobs/job_<jjjjj>.json        build bookkeeping (resume): one file per finished build job
    DIR/_networks/                    SUMO builds: generated networks (<location>.net.xml.gz), lane-geometry
                                      fingerprints (<location>.fp.npz) and index.json (location -> layout,
                                      split, network file), see `gpd_jax.data.netgeom`

Sample keys (paper configuration T=101, A=33, L=96, P=128; see `gpd_jax.data.preprocess`):

    xy              f32[n, T, A, 2]   agent box centres, scene frame (ego frame of frame 20)
    heading         f32[n, T, A]      agent headings, scene frame, [-pi, pi)
    valid           bool[n, T, A]     agent observed; slot 0 = ego (valid in every frame)
    size            f32[n, A, 2]      (length, width) in metres
    agent_type      i8[n, A]          index into gpd_jax.scene.AGENT_TYPES
    ego_pose        f32[n, T, 3]      ego (x, y, heading) per frame in the scene frame
    polylines       f32[n, L, P, 2]   lane centrelines in the scene frame, 1 m spacing, clipped to what the
                                      ego's 64x64 m window sees over the sample
    polyline_valid  bool[n, L, P]     which polyline points exist (a prefix of each row)
    road_polygons   f32[n, G, V, 2]   drivable-area rings in the scene frame (G=64 rings of V=32 vertices; a
                                      prefix of each row valid, closed implicitly): per kind the rings of the
                                      union of that kind's areas, clipped to the sample's region; even-odd
                                      rule per kind (see `gpd_jax.geometry`, `gpd_jax.data.roadgeom`)
    road_polygon_valid bool[n, G, V]  which ring vertices exist
    road_polygon_kind  i8[n, G]       index into gpd_jax.geometry.AREA_KINDS (lane, junction, other)
    road_edges      f32[n, E, Pe, 2]  road edges (boundary of the union of all areas) in the scene frame,
                                      E=64 runs of Pe=32 points
    road_edge_valid bool[n, E, Pe]    which edge points exist (a prefix of each row)
    road_map_edges  f32[n, E, Pe, 2]  (format 2) the map's road edges, drivable side on their left: the source's
                                      own road-edge lines or its areas' outline (`gpd_jax.data.roadgeom`)
    road_map_edge_valid bool[n, E, Pe] which map-edge points exist (a prefix of each row)
    road_edge_source i8[n]            (format 2) index into gpd_jax.geometry.EDGE_SOURCES: where the map edges
                                      come from (none, lane_union, drivable_area, map_lines)
    signal_state    i8[n, T, S]       (format 2) traffic-light state per frame and signal slot (S=32), WOSAC's
                                      lane-state enum gpd_jax.geometry.SIGNAL_STATES (0 unknown / no signal)
    signal_stop     f32[n, S, 2]      stop point of each signal slot, scene frame
    signal_lane     f32[n, S, Q, 2]   the controlled lane around the stop point (Q=16 points, 1 m apart)
    signal_lane_valid bool[n, S, Q]   which lane points exist; see `gpd_jax.data.signals`

The loader makes `Scene.road` (`gpd_jax.geometry.RoadGeometry`) from the road keys with the polylines as its
lane centrelines, with the map edges where every shard has them, and `Scene.signals`
(`gpd_jax.geometry.TrafficSignals`) from the signal keys where every shard has them (None otherwise: format-1
stores, read as before). Stores built before the road geometry existed lack the five road keys: they stay readable
(`Shard.has_road` False, `Scene.road` None) and consumers that need the geometry refuse with
`gpd_jax.geometry.ROAD_MISSING` ("rebuild with python -m gpd_jax.data build ..."). A source without map
geometry writes all-invalid road arrays (counted as `samples_without_road_geometry` in the build statistics).

About 190 kB per sample (98 kB of it lanes, 37 kB road geometry). Shards are written to a hidden temporary directory in the split directory and
renamed into place when complete (`os.replace`), so a shard directory that exists is complete; leftover
temporaries from a killed build are ignored and removed by the next build. Files are plain `.npy` so
that readers memory-map them (memory stays flat whatever the dataset size).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import threading
from typing import Any

import numpy as np

from gpd_jax.data.errors import DataError
from gpd_jax.data.preprocess import SAMPLE_SPEC
from gpd_jax.data.roadgeom import MAP_EDGE_KEYS, ROAD_KEYS
from gpd_jax.data.signals import SIGNAL_KEYS
from gpd_jax import fsutil
from gpd_jax.fsutil import umask_mode

# 2: map road edges (`MAP_EDGE_KEYS`) and traffic-light states (`SIGNAL_KEYS`) added; format-1 stores still read
FORMAT_VERSION = 2
OPTIONAL_GROUPS = (MAP_EDGE_KEYS, SIGNAL_KEYS)  # keys a shard may lack as a whole group (older formats)
MANIFEST = "dataset.json"
SPLITS = ("train", "val", "test")
MAP_TOKENS = "map_tokens.npy"
MAP_TOKENS_SOURCE = "map_tokens.json"  # which tokenizer wrote map_tokens.npy (see `save_map_tokens`)
NUM_MAP_TOKENS = 64
MISSING_MAP_TOKEN = 255  # u8 value filling every token of a frame whose map was not encoded


def shard_name(index: int) -> str:
    return f"shard_{int(index):05d}"


def shard_dir(data_dir: str, split: str, index: int) -> str:
    return os.path.join(data_dir, split, shard_name(index))


def atomic_write_json(path: str, obj: Any) -> None:
    fsutil.atomic_write_json(path, obj, indent=1)


def atomic_save_npy(path: str, arr: np.ndarray) -> None:
    with fsutil.atomic_file(path, "wb") as f:
        np.save(f, arr)


def stack_samples(samples: list[dict[str, np.ndarray]], spec=SAMPLE_SPEC) -> dict[str, np.ndarray]:
    """List of per-sample dicts -> dict of stacked arrays with the spec's dtypes (checked shapes)."""
    out = {}
    for k, (shape, dtype) in spec.items():
        arr = np.stack([np.asarray(s[k]) for s in samples]).astype(dtype, copy=False)
        if arr.shape[1:] != tuple(shape):
            raise ValueError(f"sample key {k}: shape {arr.shape[1:]}, expected {tuple(shape)}")
        out[k] = arr
    return out


def write_shard(data_dir: str, split: str, index: int, arrays: dict[str, np.ndarray],
                scenario_ids: list[str], locations: list[str], extra: dict | None = None) -> str:
    """Writes one shard atomically (temp dir, then rename). Returns its directory."""
    n = len(scenario_ids)
    if n == 0:
        raise ValueError("refusing to write an empty shard")
    for k, a in arrays.items():
        if a.shape[0] != n:
            raise ValueError(f"key {k} has {a.shape[0]} samples, expected {n}")
    split_dir = os.path.join(data_dir, split)
    os.makedirs(split_dir, exist_ok=True)
    final = shard_dir(data_dir, split, index)
    if os.path.exists(final):
        raise FileExistsError(final)
    tmp = tempfile.mkdtemp(dir=split_dir, prefix=f".tmp-{shard_name(index)}-")
    try:
        keys = {}
        for k, a in arrays.items():
            np.save(os.path.join(tmp, f"{k}.npy"), a)
            keys[k] = {"dtype": str(a.dtype), "shape": list(a.shape[1:]),
                       "nbytes": os.path.getsize(os.path.join(tmp, f"{k}.npy"))}
        meta = {"format_version": FORMAT_VERSION, "num_samples": n, "keys": keys,
                "scenario_ids": list(scenario_ids), "locations": list(locations), **(extra or {})}
        with open(os.path.join(tmp, "meta.json"), "w") as f:
            json.dump(meta, f)
        umask_mode(tmp, directory=True)
        os.replace(tmp, final)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return final


def list_shards(data_dir: str, split: str) -> list[str]:
    """Complete shard directories of a split, sorted by index (temporaries ignored)."""
    d = os.path.join(data_dir, split)
    if not os.path.isdir(d):
        return []
    return [os.path.join(d, n) for n in sorted(os.listdir(d)) if n.startswith("shard_")
            and os.path.isdir(os.path.join(d, n))]


def list_splits(data_dir: str) -> list[str]:
    if not os.path.isdir(data_dir):
        raise DataError(data_dir, "dataset directory not found")
    return sorted(n for n in os.listdir(data_dir) if not n.startswith((".", "_"))
                  and os.path.isdir(os.path.join(data_dir, n)))


def clean_temporaries(data_dir: str) -> int:
    """Removes leftover temporary shards/files of an interrupted build. Returns how many."""
    n = 0
    if not os.path.isdir(data_dir):
        return 0
    for root, dirs, files in os.walk(data_dir):
        for name in list(dirs):
            if name.startswith(".tmp-"):
                shutil.rmtree(os.path.join(root, name), ignore_errors=True)
                dirs.remove(name)
                n += 1
        for name in files:
            if name.startswith(".tmp-"):
                os.remove(os.path.join(root, name))
                n += 1
    return n


# numpy parses a .npy header with `ast.literal_eval`, which CPython 3.11 (up to at least 3.11.7) cannot run in two
# threads at once: it fails with "SystemError: AST constructor recursion depth mismatch". grain's reader threads
# open shards concurrently (a store mixture opens several at a time), so headers are read one at a time.
_NPY_HEADER_LOCK = threading.Lock()


def _open_npy(path: str) -> np.ndarray:
    """A read-only memory map of a .npy file (no pickles); the header is parsed under `_NPY_HEADER_LOCK`."""
    with _NPY_HEADER_LOCK:
        return np.load(path, mmap_mode="r", allow_pickle=False)


def _npy_problem(e: BaseException) -> str:
    """What is wrong with a .npy file numpy refused, in one line, without numpy's advice to allow pickles (a store
    never holds Python objects, and a file that declares them is damaged or foreign: it is never unpickled)."""
    msg = " ".join(str(e).split())
    if "allow_pickle" in msg or "Python objects" in msg:
        return ("its header declares Python objects (object dtype), which a store never holds: the file is damaged "
                "or not from a store; rebuild this shard (rerun the build, which resumes)")
    return f"{msg[:200]}; rebuild this shard (rerun the build, which resumes)"


class Shard:
    """A complete shard, validated on open and read through memory maps.

    Raises `DataError` naming the file if `meta.json` is missing or unreadable, a key file is missing,
    truncated (size differs from the recorded one) or has the wrong dtype / shape.
    """

    def __init__(self, path: str, spec=SAMPLE_SPEC):
        self.path = path
        mpath = os.path.join(path, "meta.json")
        try:
            with open(mpath) as f:
                meta = json.load(f)
        except FileNotFoundError as e:
            raise DataError(mpath, "shard has no meta.json (incomplete or not a shard)") from e
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise DataError(mpath, f"corrupt meta.json: {e}") from e
        self.meta = meta
        n = meta.get("num_samples")
        if not isinstance(n, int) or n <= 0:
            raise DataError(mpath, f"bad num_samples {n!r}")
        self.num_samples = n
        self.arrays: dict[str, np.ndarray] = {}
        present = meta.get("keys", {})
        road_present = [k for k in ROAD_KEYS if k in present]
        if road_present and len(road_present) != len(ROAD_KEYS):
            raise DataError(mpath, f"road geometry keys incomplete: has {road_present}, needs all of {ROAD_KEYS}")
        # stores of format 1 have neither the map edges nor the signals: readable, `has_map_edges` /
        # `has_signals` False (the realism metric then orients the road edges itself and leaves out the
        # traffic-light term)
        optional = {}
        for group in OPTIONAL_GROUPS:
            got = [k for k in group if k in present]
            if got and len(got) != len(group):
                raise DataError(mpath, f"keys incomplete: has {got}, needs all of {group}")
            optional.update({k: bool(got) for k in group})
        self.has_map_edges = all(optional[k] for k in MAP_EDGE_KEYS)
        self.has_signals = all(optional[k] for k in SIGNAL_KEYS)
        # stores built before the road geometry existed have none of its keys: readable, `has_road` False
        self.has_road = bool(road_present)
        for k, (shape, dtype) in spec.items():
            f = os.path.join(path, f"{k}.npy")
            info = meta.get("keys", {}).get(k)
            if info is None and (k in ROAD_KEYS and not self.has_road or k in optional and not optional[k]):
                continue
            if info is None:
                raise DataError(mpath, f"key {k!r} missing from the shard's meta.json")
            if spec is SAMPLE_SPEC:  # sizes (T, A, L, P) come from the build's config; ranks must match
                shape = tuple(info.get("shape", ()))
                if len(shape) != len(SAMPLE_SPEC[k][0]):
                    raise DataError(mpath, f"key {k!r}: shape {shape} has the wrong rank")
            if not os.path.isfile(f):
                raise DataError(f, "file missing from shard")
            size = os.path.getsize(f)
            if size != info.get("nbytes"):
                raise DataError(f, f"truncated or corrupt: {size} bytes, meta.json says {info.get('nbytes')}")
            try:
                a = _open_npy(f)
            except (ValueError, OSError, EOFError) as e:
                raise DataError(f, f"unreadable .npy: {_npy_problem(e)}") from e
            if a.shape != (n, *shape) or a.dtype != np.dtype(dtype):
                raise DataError(f, f"shape {a.shape} dtype {a.dtype}, expected {(n, *shape)} {dtype}")
            self.arrays[k] = a
        self.map_tokens = None
        tp = os.path.join(path, MAP_TOKENS)
        if os.path.isfile(tp):
            try:
                t = _open_npy(tp)
            except (ValueError, OSError, EOFError) as e:
                raise DataError(tp, f"unreadable map tokens: {_npy_problem(e)}") from e
            T = spec["xy"][0][0]
            if t.shape != (n, T, NUM_MAP_TOKENS):
                raise DataError(tp, f"map tokens shape {t.shape}, expected {(n, T, NUM_MAP_TOKENS)}")
            self.map_tokens = t

    def read(self, i: int, keys=None) -> dict[str, np.ndarray]:
        """Sample i as a dict of arrays (copies). Raises DataError on non-finite agent or lane values."""
        keys = self.arrays.keys() if keys is None else keys
        out = {k: np.array(self.arrays[k][i]) for k in keys}
        for k, vk in (("xy", "valid"), ("heading", "valid"), ("ego_pose", None), ("polylines", "polyline_valid"),
                      ("road_polygons", "road_polygon_valid"), ("road_edges", "road_edge_valid"),
                      ("road_map_edges", "road_map_edge_valid"), ("signal_stop", None),
                      ("signal_lane", "signal_lane_valid")):
            if k in out:
                a = out[k]
                m = out.get(vk) if vk else None
                bad = ~np.isfinite(a) if m is None else (~np.isfinite(a) & (m if a.ndim == m.ndim else m[..., None]))
                if bad.any():
                    raise DataError(os.path.join(self.path, f"{k}.npy"), f"sample {i}: non-finite values")
        return out


def save_map_tokens(data_dir: str, split: str, shard_index: int, tokens: np.ndarray,
                    tokenizer: str | None = None, frame_stride: int = 1) -> str:
    """Stores the map tokenizer's tokens of one shard next to its samples (atomic write).

    Args:
      data_dir: the dataset directory.
      split: split name.
      shard_index: the shard's index j (directory `shard_<jjjjj>`; see `shard_indices`).
      tokens: uint8/int[n, T, 64] codebook indices in [0, 254], n = the shard's sample count; a frame whose
        map was not encoded has MISSING_MAP_TOKEN (255) in all 64 places (the loader marks it `map_valid`
        False).
      tokenizer: an identifier of the tokenizer that produced them (`MapTokenizer.fingerprint`), recorded in
        `<shard>/map_tokens.json` so that a later `encode` can skip shards it already did.
      frame_stride: which frames were encoded (0, s, 2s, ...), recorded with `tokenizer`.
    Returns the written path (`<shard>/map_tokens.npy`, stored as uint8).
    """
    path = shard_dir(data_dir, split, shard_index)
    meta_path = os.path.join(path, "meta.json")
    if not os.path.isfile(meta_path):
        raise DataError(path, "no such complete shard")
    with open(meta_path) as f:
        meta = json.load(f)
    n, T = meta["num_samples"], meta["keys"]["xy"]["shape"][0]
    tokens = np.asarray(tokens)
    if tokens.shape != (n, T, NUM_MAP_TOKENS):
        raise ValueError(f"tokens shape {tokens.shape}, expected {(n, T, NUM_MAP_TOKENS)} for {path}")
    if tokens.dtype.kind not in "iu" or tokens.size and (tokens.min() < 0 or tokens.max() > MISSING_MAP_TOKEN):
        raise ValueError(f"map tokens must be integers in [0, {MISSING_MAP_TOKEN - 1}] ({MISSING_MAP_TOKEN} for "
                         f"frames not encoded), {path}")
    missing = tokens == MISSING_MAP_TOKEN
    if (missing.any(-1) != missing.all(-1)).any():
        raise ValueError(f"map token {MISSING_MAP_TOKEN} marks whole frames that were not encoded; {path} has "
                         "frames where only some tokens have it")
    out = os.path.join(path, MAP_TOKENS)
    src = os.path.join(path, MAP_TOKENS_SOURCE)
    if os.path.exists(src):  # never leave a stale record beside new tokens
        os.remove(src)
    atomic_save_npy(out, tokens.astype(np.uint8))
    if tokenizer is not None:
        atomic_write_json(src, {"tokenizer": tokenizer, "shape": list(tokens.shape),
                                "frame_stride": int(frame_stride)})
    return out


def map_tokens_record(data_dir: str, split: str, shard_index: int) -> dict | None:
    """What `save_map_tokens` recorded with a shard's map tokens ({"tokenizer", "shape", "frame_stride"};
    frame_stride 1 for records that predate it), or None (no tokens, or no record)."""
    path = shard_dir(data_dir, split, shard_index)
    if not os.path.isfile(os.path.join(path, MAP_TOKENS)):
        return None
    try:
        with open(os.path.join(path, MAP_TOKENS_SOURCE)) as f:
            rec = json.load(f)
        return {"frame_stride": 1} | rec if isinstance(rec, dict) else None
    except (OSError, ValueError):
        return None


def map_tokens_source(data_dir: str, split: str, shard_index: int) -> str | None:
    """The `tokenizer` identifier recorded with a shard's map tokens, or None (no tokens, or no record)."""
    rec = map_tokens_record(data_dir, split, shard_index)
    return None if rec is None else rec.get("tokenizer")


def foreign_map_token_shards(data_dir: str, split: str, fingerprint: str) -> list[int]:
    """Positions (in `list_shards` order) of the shards of a split whose map tokens were recorded as made by a
    tokenizer other than `fingerprint` (`MapTokenizer.fingerprint`). Shards without tokens, or with tokens of
    unknown origin (no record), are not listed."""
    bad = []
    for pos, j in enumerate(shard_indices(data_dir, split)):
        src = map_tokens_source(data_dir, split, j)
        if src is not None and src != fingerprint:
            bad.append(pos)
    return bad


def shard_indices(data_dir: str, split: str) -> list[int]:
    """Indices j of the complete shards of a split (for `save_map_tokens`)."""
    return [int(os.path.basename(p)[len("shard_"):]) for p in list_shards(data_dir, split)]


def sample_layouts(data_dir: str, split: str) -> list[str]:
    """The network layout of every sample of a split, in loader order (shard by shard): "grid", "spider",
    "random" (generated SUMO networks), "real" (SUMO's real networks), "given" (other --net files), or
    "unknown" (other sources, or stores built before layouts were recorded). Read from each shard's
    `meta.json` ("layout"), which SUMO builds write."""
    out: list[str] = []
    for p in list_shards(data_dir, split):
        try:
            with open(os.path.join(p, "meta.json")) as f:
                meta = json.load(f)
        except (OSError, json.JSONDecodeError) as e:
            raise DataError(os.path.join(p, "meta.json"), f"unreadable shard metadata: {e}") from e
        out += [meta.get("layout") or "unknown"] * int(meta["num_samples"])
    return out


def read_manifest(data_dir: str) -> dict:
    p = os.path.join(data_dir, MANIFEST)
    try:
        with open(p) as f:
            return json.load(f)
    except FileNotFoundError as e:
        raise DataError(p, "no dataset manifest (build not finished?)") from e
    except json.JSONDecodeError as e:
        raise DataError(p, f"corrupt manifest: {e}") from e


def write_manifest(data_dir: str, extra: dict | None = None, spec=SAMPLE_SPEC) -> dict:
    """(Re)writes `DIR/dataset.json` from the complete shards on disk."""
    splits = {}
    for split in list_splits(data_dir):
        shards = []
        for p in list_shards(data_dir, split):
            try:
                with open(os.path.join(p, "meta.json")) as f:
                    meta = json.load(f)
            except (OSError, json.JSONDecodeError):
                continue
            shards.append({"index": int(os.path.basename(p)[6:]), "num_samples": meta["num_samples"],
                           "locations": sorted(set(meta.get("locations", []))),
                           **({"layout": meta["layout"]} if meta.get("layout") else {})})
        splits[split] = {"num_samples": sum(s["num_samples"] for s in shards), "num_shards": len(shards),
                         "shards": shards}
    manifest = {
        "format_version": FORMAT_VERSION,
        "layout": "DIR/<split>/shard_<jjjjj>/<key>.npy (+ meta.json, optional map_tokens.npy u8[n, T, 64])",
        "keys": {k: {"dtype": d, "shape": ["n", *s]} for k, (s, d) in spec.items()},
        "optional_keys": {"map_tokens": {"dtype": "uint8", "shape": ["n", spec["xy"][0][0], NUM_MAP_TOKENS]}},
        "conventions": "scene frame = ego frame of frame 20 (x forward, y left, CCW heading); slot 0 = ego; "
                       "polylines in the scene frame; map of frame t in the frame of ego_pose[t]",
        "splits": splits,
        "num_samples": sum(s["num_samples"] for s in splits.values()),
        **(extra or {}),
    }
    atomic_write_json(os.path.join(data_dir, MANIFEST), manifest)
    return manifest
