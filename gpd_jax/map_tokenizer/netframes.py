"""Map-only training frames for the map tokenizer: many road networks, ego poses drawn on their lanes, no traffic.

The lane decoder has to learn where a road's lines start and end from the raster alone, and a store built from
simulated traffic shows it few networks (data/legacy_train: 60; the shipped tokenizer's sumo6k: 192). On the
networks it trained on the shipped tokenizer reaches a paper F1 of 0.88; on held-out ones 0.65 (generated) and
0.07-0.13 (real). A map needs no traffic: a network costs ~0.4 s of netgenerate, so thousands of them, plus the
real training tiles from every angle, are cheap.

A netframes directory holds one `<name>.lanes.npz` per network (its lane centrelines resampled every 1 m,
chained as the stores chain them: `sumo_networks.read_network_lanes`, `preprocess.lane_points`; no pickles) and
`netframes.json` (per network: source, layout, left-hand, lane km, file). `build_netframes` makes it (resumes:
networks already there are kept); `pack_netframes` makes it a `.tar.xz` that `tar xf` turns back into a netframes
directory, ~13x smaller (coordinates rounded to the centimetre, stored as deltas), to carry to another machine. `frame_batches` draws a network uniformly, a point uniformly along its lanes,
the ego pose on it (heading along the lane plus N(0, `heading_sd`), a lateral offset N(0, `lateral_sd`)), and
clips the lanes to the ego window exactly as a store sample does (`preprocess.clip_lanes`); the items are those of
`gpd_jax.map_tokenizer.store` (polylines and pose in one frame, SLEDGE vector lanes as targets), so a netframes
directory can stand in a training mixture beside stores (`--config.data.dir=NETFRAMES:0.5,STORE:0.5`).

Generated networks come from `sumo_networks.random_net_spec` with seeds drawn from `SeedSequence([seed, 4321])`, a
stream no store build uses (stores draw theirs from `[seed, 1234]`); real maps are given files in any format
`gpd_jax.data.sources.maps.read_map_lanes` reads (SUMO networks, Lanelet2, CommonRoad, Apollo HD maps; keep held-out
places out: `gpd_jax.data.sources.realnets.TEST_ONLY`, docs/data.md's map splits), optionally with a left-hand copy
each. A netframes directory of held-out maps is also an evaluation set: `frame_batches` with `max_batches` draws the
same frames for every tokenizer (`python -m gpd_jax.map_tokenizer evaluate --data NETFRAMES --max-batches N`).
"""

from __future__ import annotations

import json
import os
import time
from typing import Iterator, Sequence

import numpy as np

from gpd_jax.data.errors import DataError
from gpd_jax.data.lanes import vector_lanes
from gpd_jax.data.preprocess import SampleConfig, clip_lanes, lane_points, LanePoints
from gpd_jax.data.store import atomic_write_json

MANIFEST = "netframes.json"


def is_netframes(path: str) -> bool:
    """Whether `path` is a netframes directory (holds `netframes.json`)."""
    return os.path.isfile(os.path.join(path, MANIFEST))


def _save_lanes(lp: LanePoints, path: str) -> None:
    tmp = path + f".tmp-{os.getpid()}.npz"
    np.savez_compressed(tmp, xy=lp.xy.astype(np.float32), line=lp.line.astype(np.int32))
    os.replace(tmp, path)


def _network_record(name: str, lanes, path: str, out_dir: str, source: str, layout: str, spacing: float) -> dict:
    lp = lane_points(lanes, spacing)
    if len(lp.xy) < 2:
        raise DataError(path, "map has no lane of 2 m or more")
    f = f"{name}.lanes.npz"
    _save_lanes(lp, os.path.join(out_dir, f))
    km = float(sum(np.linalg.norm(np.diff(p, axis=0), axis=-1).sum() for p in lanes)) / 1000.0
    return {"name": name, "file": f, "source": source, "layout": layout,
            "lane_km": round(km, 3), "points": int(len(lp.xy))}


def _real_lanes(path: str, lefthand: bool, tmp: str, ignore_turnarounds: bool) -> tuple[tuple, str, bool]:
    """(lanes, format, left-hand) of a real map file; `lefthand` asks for its left-hand copy (SUMO: rebuilt by
    netconvert; other formats: mirrored, `gpd_jax.data.sources.maps.mirror_lanes`)."""
    from gpd_jax.data.sources import maps, sumo_networks

    fmt = maps.map_format(path)
    if fmt == "sumo":
        net = sumo_networks.make_lefthand(path, os.path.join(tmp, "lh.net.xml")) if lefthand else path
        return (sumo_networks.read_network_lanes(net, ignore_turnarounds=ignore_turnarounds), fmt,
                sumo_networks.is_lefthand(net))
    lanes = maps.read_map_lanes(path)
    return (maps.mirror_lanes(lanes) if lefthand else lanes), fmt, lefthand


def build_netframes(out_dir: str, num_generated: int = 0, seed: int = 0, real_nets: Sequence[str] = (),
                    real_lefthand: bool = False, lefthand_share: float = 0.25, curved_share: float = 0.5,
                    ignore_turnarounds: bool = False, log=print) -> dict:
    """Builds (or completes) a netframes directory; returns its manifest.

    Args:
      num_generated: generated networks (`sumo_networks.random_net_spec` over grid / spider / random layouts).
      seed: their seed stream (`SeedSequence([seed, 4321])`).
      real_nets: real map files used as they are, in any format `gpd_jax.data.sources.maps.read_map_lanes` reads
        (SUMO networks such as the `gpd_jax.data.sources.realnets` training tiles, Lanelet2, CommonRoad, Apollo);
        the record's `layout` is the format.
      real_lefthand: also a left-hand copy of each real map (SUMO: `sumo_networks.make_lefthand`; other
        formats: mirrored).
      lefthand_share / curved_share: probabilities for generated networks (`sumo_networks.random_net_spec`).
      ignore_turnarounds: chain lanes through SUMO's turnaround connectors (`sumo_networks.read_network_lanes`); the
        stores do not, so keep the default for a tokenizer whose targets must match theirs.
    """
    import tempfile

    from gpd_jax.data.sources import sumo_networks

    os.makedirs(out_dir, exist_ok=True)
    path = os.path.join(out_dir, MANIFEST)
    settings = {"num_generated": int(num_generated), "seed": int(seed), "lefthand_share": float(lefthand_share),
                "curved_share": float(curved_share), "real_nets": [os.path.basename(p) for p in real_nets],
                "real_lefthand": bool(real_lefthand), "ignore_turnarounds": bool(ignore_turnarounds),
                "lane_spacing": SampleConfig().lane_spacing}
    old = {}
    if os.path.isfile(path):
        with open(path) as f:
            man = json.load(f)
        if man.get("settings") != settings:
            raise DataError(out_dir, f"holds netframes built with other settings ({man.get('settings')}); "
                                     "use another directory")
        old = {r["name"]: r for r in man.get("networks", [])}
    records = dict(old)
    t0 = time.time()

    def save():
        atomic_write_json(path, {"format_version": 1, "settings": settings,
                                 "networks": [records[k] for k in sorted(records)],
                                 "num_networks": len(records)})

    seeds = [int(s.generate_state(1)[0]) for s in np.random.SeedSequence([seed, 4321]).spawn(num_generated)]
    with tempfile.TemporaryDirectory(prefix="netframes_", dir=out_dir) as tmp:
        for i, s in enumerate(seeds):
            name = f"gen_{seed}_{i:05d}"
            if name in records and os.path.isfile(os.path.join(out_dir, records[name]["file"])):
                continue
            spec = sumo_networks.random_net_spec(s, None, lefthand_share, 0.0, curved_share)
            net = sumo_networks.generate_network(spec, os.path.join(tmp, "net.net.xml"))
            lanes = sumo_networks.read_network_lanes(net, ignore_turnarounds=ignore_turnarounds)
            records[name] = _network_record(name, lanes, net, out_dir, "generated", spec.layout,
                                            settings["lane_spacing"])
            records[name]["lefthand"] = sumo_networks.is_lefthand(net)
            records[name]["bend"] = round(spec.bend, 4)
            if (i + 1) % 50 == 0:
                save()
                log(f"netframes: {i + 1} / {num_generated} generated networks ({time.time() - t0:.0f} s)")
        for p in real_nets:
            base = os.path.basename(p).split(".")[0]
            for lh in ([False, True] if real_lefthand else [False]):
                name = f"real_{base}" + ("_lh" if lh else "")
                if name in records and os.path.isfile(os.path.join(out_dir, records[name]["file"])):
                    continue
                lanes, fmt, lefthand = _real_lanes(p, lh, tmp, ignore_turnarounds)
                records[name] = _network_record(name, lanes, p, out_dir, "real", fmt, settings["lane_spacing"])
                records[name]["lefthand"] = lefthand
                save()
    save()
    log(f"netframes: {len(records)} networks in {out_dir} ({time.time() - t0:.0f} s)")
    with open(path) as f:
        return json.load(f)


def _read_lanes(path: str) -> tuple[np.ndarray, np.ndarray]:
    """(xy f64[N, 2], line i32[N]) of a network's lane file, built (`xy`) or packed (`dxy_cm`, centimetre
    deltas: `pack_netframes`). Raises DataError naming the file."""
    try:
        with np.load(path, allow_pickle=False) as z:
            line = np.asarray(z["line"], np.int32)
            if "dxy_cm" in z:
                return np.cumsum(np.asarray(z["dxy_cm"], np.int64), axis=0) / 100.0, line
            return np.asarray(z["xy"], np.float64), line
    except (OSError, KeyError, ValueError) as e:
        raise DataError(path, f"unreadable lane file: {e}") from None


class NetFrames:
    """The networks of a netframes directory, loaded once (lane points f32, ~0.1 MB per generated network)."""

    def __init__(self, path: str):
        if not is_netframes(path):
            raise DataError(path, f"not a netframes directory (no {MANIFEST}); build one with "
                                  "`python -m gpd_jax.map_tokenizer netframes`")
        with open(os.path.join(path, MANIFEST)) as f:
            self.manifest = json.load(f)
        self.lanes: list[LanePoints] = []
        self.names: list[str] = []
        for r in self.manifest["networks"]:
            xy, line = _read_lanes(os.path.join(path, r["file"]))
            if xy.ndim != 2 or xy.shape[1:] != (2,) or len(line) != len(xy) or len(xy) < 2:
                raise DataError(os.path.join(path, r["file"]), f"lane points of shape {xy.shape} / {line.shape}")
            self.lanes.append(LanePoints(xy, line))
            self.names.append(r["name"])
        if not self.lanes:
            raise DataError(path, "holds no network")

    def item(self, rng: np.random.Generator, heading_sd: float = 0.05, lateral_sd: float = 0.3,
             cfg: SampleConfig = SampleConfig(), gt_recut: str | None = None) -> dict[str, np.ndarray]:
        """One frame (the items of `gpd_jax.map_tokenizer.store`): a random network, a pose on one of its lanes;
        `gt_recut` as in `gpd_jax.map_tokenizer.store.frame_batches`."""
        k = int(rng.integers(len(self.lanes)))
        lp = self.lanes[k]
        while True:  # a point with a successor on its own line gives the lane's heading there
            j = int(rng.integers(len(lp.xy) - 1))
            if lp.line[j + 1] == lp.line[j]:
                break
        d = lp.xy[j + 1] - lp.xy[j]
        h = float(np.arctan2(d[1], d[0]) + rng.normal(0.0, heading_sd))
        off = rng.normal(0.0, lateral_sd)
        xy = lp.xy[j] + rng.uniform() * d + off * np.array([-np.sin(h), np.cos(h)])
        world_pose = np.array([xy[0], xy[1], h])
        pose = np.zeros((1, 3))
        poly, ok = clip_lanes(lp, world_pose, pose, cfg)
        lanes, lvalid = vector_lanes(poly, ok, pose[0], recut=gt_recut)
        return dict(polylines=poly, polyline_valid=ok, pose=pose[0].astype(np.float32),
                    lanes=lanes.astype(np.float32), lanes_valid=lvalid, sample=np.int32(k), frame=np.int32(0))

    def walk(self, seed: int, **kw) -> Iterator[dict[str, np.ndarray]]:
        """Endless items, deterministic in `seed`."""
        rng = np.random.default_rng((seed, 77))
        while True:
            yield self.item(rng, **kw)


def pack_netframes(path: str, out_dir: str, max_networks: int | None = None, preset: int = 6) -> str:
    """Writes `out_dir/<name>.tar.xz` holding the netframes directory `path` (named `<name>`, its basename): its
    manifest (the first `max_networks` networks, with a "packed" record) and each network's lane points as
    centimetre-rounded deltas (`dxy_cm` i32[N, 2], `line` i32[N]; at most 5 mm off, which `NetFrames` reads like
    the original). `tar xf ARCHIVE -C DIR` gives DIR/<name>, a netframes directory. Written to a temporary file
    and renamed; an archive already there is kept (a stopped packing resumes). Returns the archive's path."""
    import io
    import tarfile

    if not is_netframes(path):
        raise DataError(path, f"not a netframes directory (no {MANIFEST})")
    name = os.path.basename(os.path.normpath(path))
    archive = os.path.join(out_dir, f"{name}.tar.xz")
    if os.path.exists(archive):
        return archive
    with open(os.path.join(path, MANIFEST)) as f:
        manifest = json.load(f)
    if max_networks is not None:
        if max_networks < 1:
            raise DataError(path, f"max_networks must be >= 1, got {max_networks}")
        manifest["networks"] = manifest["networks"][:max_networks]
        manifest["num_networks"] = len(manifest["networks"])
    manifest["packed"] = {"source": os.path.abspath(path), "coordinates": "centimetre deltas (dxy_cm)"}

    def add(tf, arc: str, data: bytes) -> None:
        info = tarfile.TarInfo(arc)
        info.size = len(data)
        info.mtime = int(time.time())
        tf.addfile(info, io.BytesIO(data))

    os.makedirs(out_dir, exist_ok=True)
    tmp = archive + f".tmp-{os.getpid()}"
    try:
        with tarfile.open(tmp, "w:xz", preset=preset) as tf:
            add(tf, f"{name}/{MANIFEST}", json.dumps(manifest, indent=1).encode())
            for r in manifest["networks"]:
                f = os.path.join(path, r["file"])
                xy, line = _read_lanes(f)
                q = np.round(xy * 100.0).astype(np.int64)
                if np.abs(q).max(initial=0) >= 2**31 // 2:
                    raise DataError(f, "coordinates beyond the packable range (+-10,000 km)")
                d = np.diff(q, axis=0, prepend=np.zeros((1, 2), np.int64)).astype(np.int32)
                buf = io.BytesIO()
                np.savez(buf, dxy_cm=d, line=line)  # uncompressed: xz compresses the small deltas
                add(tf, f"{name}/{r['file']}", buf.getvalue())
        os.replace(tmp, archive)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return archive
