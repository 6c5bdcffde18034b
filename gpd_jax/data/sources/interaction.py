"""The INTERACTION importer: the drone recordings of the INTERACTION dataset (10 Hz vehicle tracks over
roundabouts, intersections and merges, with Lanelet2 maps) -> `RawLog` -> a store (`build_interaction`, with the
shared job runner `gpd_jax.data.jobs`).

Input (`find_track_files`): the dataset's root folder with `recorded_trackfiles/<site>/vehicle_tracks_<nnn>.csv`
and `maps/<site>.osm` (the layout of the INTERACTION release and of its copy in the GitHub repository
`gaoyinfeng/TrajGen`; docs/data.md says where to get it and under what terms). A site is a place (one road layout
filmed from a drone), e.g. `DR_USA_Roundabout_FT`; each track file is one recording there.

What is read, and the conventions:

* **Tracks** (`read_tracks`): a CSV with a header naming at least `TRACK_COLUMNS` (in any order; `vx`, `vy` are
  used for the heading check only): one row per track and frame, `frame_id` counting 100 ms frames
  (`timestamp_ms` = 100 x `frame_id` in the release). The frames of a file are its 10 Hz timeline from its first
  `frame_id`; a track missing in some frames is invalid there. A file whose timestamps are not 100 ms apart per
  frame, or that lists a track twice in one frame, is refused.
* **Agents.** Rows whose `agent_type` is in `VEHICLE_TYPES` (`car`, `truck`, and the `truck_bus` / `bus` labels of
  other releases) are kept, the class from that label. Pedestrians and bicycles (in `pedestrian_tracks_*.csv`
  files of the release, which are not read) and any other type are dropped and counted (`tracks_dropped_<type>`).
  Positions `x`, `y` are metres in the map's local frame, headings `psi_rad` radians counter-clockwise from +x -
  the store's conventions. Sizes: the median `length` / `width` of a track (constant in the release); a track
  without positive sizes gets `DEFAULT_SIZE` (counted). Non-finite positions or headings make those frames
  invalid (counted).
* **Heading check.** A file whose headings disagree with the direction of the recorded velocity (`vx`, `vy`) by
  more than 90 degrees in the median over rows faster than 2 m/s is refused (degrees, another zero direction, a
  mirrored frame).
* **Map** (`gpd_jax.data.sources.lanelet2`): the site's Lanelet2 map projected as INTERACTION's own tools do
  (UTM around lat = lon = 0, the frame the track files use). Lanes are the vehicle lanelets' centrelines (the
  average of the aligned left and right bounds, in the lanelet's direction); the drivable area is the union of
  the vehicle lanelets' polygons (kind "lane": the maps mark no junction areas; keep-out multipolygons are
  counted, not used); road edges are that union's boundary (`gpd_jax.data.roadgeom`); the map road edges (what
  the realism metric reads) are the map's curbstone / road_border / guard_rail / wall / fence ways, oriented
  against that union (`lanelet2.ROAD_BORDER_TYPES`; INTERACTION's maps draw curbstones and guard rails; a map
  without any falls back to the union's outline, tagged "lane_union"). A track file whose site has no map is
  refused.
* **Ego** (`choose_windows`). A drone recording has no recording vehicle, so every window gets one: windows start
  every `WINDOW_STRIDE` frames (3 s; windows overlap, and most get a different ego); the candidates are the
  vehicles valid in all 101 frames of the window that move (their centre travels at least `MIN_EGO_TRAVEL`
  metres from the first to the last frame: parked and queued-throughout vehicles are left out, vehicles that
  wait and then go are not); one is drawn uniformly, seeded by (seed, file, start), so a build is reproducible.
  Windows without a candidate are counted (`skip_no_ego_candidate`). Everything else of a sample (the 32 nearest
  vehicles at the current frame, the scene frame, lane and road clipping) is `gpd_jax.data.preprocess.make_sample`,
  as for every source.
* **Splits** are by site (`SITE_SPLITS`, fixed before any model saw the data): every window of a site goes to its
  split. `--split S` builds the sites of split S; `--sites` names sites (each into its split, or all into `--split`
  when both are given: for your own sites; a known site put into another split is warned about).
* `RawLog.name` is `<site>/<file stem>`, `RawLog.location` the site.

Every problem with an input file raises `gpd_jax.data.errors.DataError` naming the file and the reason: a missing
column, a value that is not a number (its line and column named), a frame period that is not 100 ms, a repeated
(track, frame), headings that contradict the velocities, an unknown or unreadable map.
"""

from __future__ import annotations

import csv
import dataclasses
import glob
import hashlib
import logging
import os
import shutil
import time
import zlib
from collections import Counter

import numpy as np

from gpd_jax.data import preprocess, store
from gpd_jax.data.errors import DataError
from gpd_jax.data.jobs import check_settings, finish, job_marker, run_jobs
from gpd_jax.data.raw import RawLog
from gpd_jax.data.roadgeom import Area
from gpd_jax.geometry import AREA_KIND_ID
from gpd_jax.scene import TYPE_ID

log = logging.getLogger(__name__)

TRACKS_DIR = "recorded_trackfiles"
MAPS_DIR = "maps"
TRACK_GLOB = "vehicle_tracks_*.csv"
TRACK_COLUMNS = ("track_id", "frame_id", "timestamp_ms", "agent_type", "x", "y", "psi_rad", "length", "width")
VELOCITY_COLUMNS = ("vx", "vy")
FRAME_MS = 100
VEHICLE_TYPES = {"car": "car", "truck": "truck", "truck_bus": "truck", "bus": "bus"}
DEFAULT_SIZE = (4.6, 1.85)  # metres, for a track without positive length / width
MAP_ORIGIN = (0.0, 0.0)  # lat, lon of every INTERACTION map's local frame

WINDOW_STRIDE = 30  # frames (3 s) between window starts
MIN_EGO_TRAVEL = 10.0  # metres the ego's centre moves from the first to the last frame of its window

HEADING_CHECK_SPEED = 2.0  # m/s
HEADING_CHECK_MIN_ROWS = 20

# The split by place, fixed before any model saw INTERACTION data (docs/data.md, "INTERACTION"). The three EP sites
# share a city code and may be neighbouring streets, so they stay together (train). DR_CHN_Merging_ZS: its track
# files are missing in the gaoyinfeng/TrajGen copy (over GitHub's size limit); its map is there.
SITE_SPLITS = {
    "DR_USA_Intersection_GL": "train",
    "DR_USA_Roundabout_FT": "train",
    "DR_USA_Intersection_EP0": "train",
    "DR_USA_Intersection_EP1": "train",
    "DR_USA_Roundabout_EP": "train",
    "DR_CHN_Merging_ZS": "train",
    "DR_USA_Roundabout_SR": "val",
    "DR_USA_Intersection_MA": "test",
    "DR_CHN_Roundabout_LN": "test",
}


@dataclasses.dataclass(frozen=True)
class TrackFile:
    """One recording: `path` of its CSV, its `site`, and `key` = `<site>/<file stem>` (`RawLog.name`)."""

    path: str
    site: str
    key: str


# ---------------------------------------------------------------------------------------------------- finding
def map_path(db: str, site: str) -> str:
    return os.path.join(db, MAPS_DIR, f"{site}.osm")


def list_sites(db: str | os.PathLike) -> list[str]:
    """The sites of a dataset root that have track files (sorted). Raises `DataError` when `db` is not one."""
    db = os.fspath(db)
    tracks = os.path.join(db, TRACKS_DIR)
    if not os.path.isdir(tracks):
        raise DataError(db, f"not an INTERACTION dataset folder: no {TRACKS_DIR}/ in it (expected "
                            f"{TRACKS_DIR}/<site>/{TRACK_GLOB} and {MAPS_DIR}/<site>.osm)")
    return sorted(s for s in os.listdir(tracks) if glob.glob(os.path.join(tracks, s, TRACK_GLOB)))


def find_track_files(db: str | os.PathLike, sites=None) -> list[TrackFile]:
    """The vehicle track files of `sites` (default: every site with track files), sorted by key.

    Raises `DataError` for a folder that is not a dataset root, a named site without track files, or a site
    without its map (`maps/<site>.osm`), naming the track file and the map expected.
    """
    db = os.fspath(db)
    have = list_sites(db)
    if sites is None:
        sites = have
    out = []
    for site in sites:
        files = sorted(glob.glob(os.path.join(db, TRACKS_DIR, site, TRACK_GLOB)))
        if not files:
            raise DataError(os.path.join(db, TRACKS_DIR, site), f"site {site!r} has no {TRACK_GLOB} files "
                                                                f"(sites with tracks: {', '.join(have) or 'none'})")
        mp = map_path(db, site)
        if not os.path.isfile(mp):
            raise DataError(files[0], f"unknown map: site {site!r} has no Lanelet2 map {mp}")
        for f in files:
            out.append(TrackFile(f, site, f"{site}/{os.path.splitext(os.path.basename(f))[0]}"))
    if not out:
        raise DataError(db, f"no {TRACK_GLOB} files under {TRACKS_DIR}/")
    return sorted(out, key=lambda t: t.key)


# ------------------------------------------------------------------------------------------------------ tracks
def _numbers(col: list[str], name: str, path: str, rows: np.ndarray) -> np.ndarray:
    """A CSV column as f64[n]; DataError naming the first line whose value is not a number."""
    try:
        return np.array(col, np.float64)
    except ValueError:
        for i, v in enumerate(col):
            try:
                float(v)
            except ValueError:
                raise DataError(path, f"line {int(rows[i]) + 2}: column {name!r} = {v!r} is not a number") from None
        raise


def read_tracks(path: str | os.PathLike, site: str | None = None, stats: Counter | None = None) -> RawLog:
    """Reads one INTERACTION track file -> RawLog (no map yet; `with_map` adds it). `site`: its location (default
    the name of the folder it is in). Conventions and errors: module docstring."""
    path = os.fspath(path)
    stats = Counter() if stats is None else stats
    site = site or os.path.basename(os.path.dirname(os.path.abspath(path)))
    try:
        with open(path, newline="") as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            rows = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise DataError(path, f"cannot read the CSV file: {e}") from None
    if header is None:
        raise DataError(path, "empty file: no header line")
    header = [h.strip() for h in header]
    missing = [c for c in TRACK_COLUMNS if c not in header]
    if missing:
        raise DataError(path, f"missing column(s) {', '.join(missing)} (the header names: {', '.join(header)})")
    col = {c: header.index(c) for c in header}
    width = len(header)
    short = [i for i, r in enumerate(rows) if len(r) != width]
    if short:
        i = short[0]
        raise DataError(path, f"line {i + 2} has {len(rows[i])} fields, the header {width}")
    if not rows:
        raise DataError(path, "no track rows after the header")
    types = [r[col["agent_type"]].strip().lower() for r in rows]
    keep = np.array([t in VEHICLE_TYPES for t in types])
    dropped = Counter(t for t, _ in {(t, r[col["track_id"]].strip()) for t, k, r in zip(types, keep, rows) if not k})
    line = np.nonzero(keep)[0]
    rows = [rows[i] for i in line]
    types = [types[i] for i in line]
    if not rows:
        raise DataError(path, f"no vehicle rows (agent_type {', '.join(VEHICLE_TYPES)}); types: {dict(dropped)}")

    def num(name):
        return _numbers([r[col[name]] for r in rows], name, path, line)

    frame = num("frame_id")
    ts = num("timestamp_ms")
    x, y, psi = num("x"), num("y"), num("psi_rad")
    length, wid = num("length"), num("width")
    if not (np.isfinite(frame).all() and (frame == np.round(frame)).all()):
        i = int(np.nonzero(~(np.isfinite(frame) & (frame == np.round(frame))))[0][0])
        raise DataError(path, f"line {int(line[i]) + 2}: frame_id = {rows[i][col['frame_id']]!r} is not an integer")
    frame = frame.astype(np.int64)
    f0 = int(frame.min())
    # one timestamp per frame, 100 ms apart
    expect = ts - (frame - f0) * FRAME_MS
    if not np.isfinite(ts).all() or np.abs(expect - expect[0]).max() > 1.0:
        i = int(np.argmax(~np.isfinite(expect) | (np.abs(expect - expect[0]) > 1.0)))
        raise DataError(path, f"line {int(line[i]) + 2}: timestamp_ms {rows[i][col['timestamp_ms']]} at frame_id "
                              f"{frame[i]} is not {FRAME_MS} ms per frame from frame_id {f0} "
                              f"(timestamp {ts[np.argmin(frame)]:.0f} ms): not a 10 Hz recording")
    tid = [r[col["track_id"]].strip() for r in rows]
    names = sorted(set(tid), key=lambda s: (0, int(s), s) if s.isdigit() else (1, 0, s))
    index = {n: i for i, n in enumerate(names)}
    agent = np.array([index[t] for t in tid], np.int64)
    F, N = int(frame.max()) - f0 + 1, len(names)
    cell = (frame - f0) * N + agent
    uniq, first, cnt = np.unique(cell, return_index=True, return_counts=True)
    if (cnt > 1).any():
        j = int(np.nonzero(cnt > 1)[0][0])
        i = int(first[j])
        raise DataError(path, f"track {tid[i]} is listed more than once at frame_id {frame[i]} (line {int(line[i]) + 2})")
    if all(c in header for c in VELOCITY_COLUMNS):
        _check_heading(num("vx"), num("vy"), psi, path)
    fi, ai = frame - f0, agent
    xy = np.full((F, N, 2), np.nan)
    heading = np.full((F, N), np.nan)
    valid = np.zeros((F, N), bool)
    xy[fi, ai, 0], xy[fi, ai, 1], heading[fi, ai] = x, y, psi
    finite = np.isfinite(x) & np.isfinite(y) & np.isfinite(psi)
    valid[fi, ai] = finite
    stats["agent_frames_nonfinite_in_file"] += int((~finite).sum())
    xy[~valid] = np.nan
    heading[~valid] = np.nan
    size = np.zeros((N, 2), np.float64)
    atype = np.zeros((N,), np.int32)
    order = np.argsort(agent, kind="stable")
    bounds = np.searchsorted(agent[order], np.arange(N + 1))
    for a in range(N):
        rws = order[bounds[a]:bounds[a + 1]]
        lw = np.stack([length[rws], wid[rws]], -1)
        lw = lw[np.isfinite(lw).all(-1) & (lw > 0).all(-1)]
        if len(lw):
            size[a] = np.median(lw, axis=0)
        else:
            size[a] = DEFAULT_SIZE
            stats["agent_size_defaulted"] += 1
        kinds = Counter(types[i] for i in rws)
        atype[a] = TYPE_ID[VEHICLE_TYPES[kinds.most_common(1)[0][0]]]
    never = ~valid.any(0)
    stats["tracks_dropped_never_valid"] += int(never.sum())
    for t, n in dropped.items():
        stats[f"tracks_dropped_{t or 'unknown'}"] += n
    keep_a = np.nonzero(~never)[0]
    stats["tracks_vehicle"] += len(keep_a)
    stem = os.path.splitext(os.path.basename(path))[0]
    return RawLog(name=f"{site}/{stem}", location=site, timestamps=np.arange(F) * (FRAME_MS / 1000.0),
                  agent_ids=tuple(names[a] for a in keep_a), agent_xy=xy[:, keep_a], agent_heading=heading[:, keep_a],
                  agent_valid=valid[:, keep_a], agent_size=size[keep_a].astype(np.float32),
                  agent_type=atype[keep_a], lanes=(), ego_index=None, areas=())


def _check_heading(vx: np.ndarray, vy: np.ndarray, psi: np.ndarray, path: str) -> None:
    """Refuses a file whose headings point away from the recorded velocities (degrees, a mirrored frame, ...)."""
    speed = np.hypot(vx, vy)
    moving = np.isfinite(speed) & np.isfinite(psi) & (speed > HEADING_CHECK_SPEED)
    if moving.sum() < HEADING_CHECK_MIN_ROWS:
        return
    err = np.abs((psi[moving] - np.arctan2(vy[moving], vx[moving]) + np.pi) % (2 * np.pi) - np.pi)
    med = float(np.median(err))
    if med > np.pi / 2:
        raise DataError(path, f"psi_rad disagrees with the direction of (vx, vy) by {np.degrees(med):.0f} degrees "
                              "(median over rows faster than 2 m/s): headings are not radians counter-clockwise "
                              "from +x in the positions' frame")


# --------------------------------------------------------------------------------------------------------- map
def map_features(path: str | os.PathLike, stats: Counter | None = None) -> tuple[tuple, tuple, tuple]:
    """(lanes, areas, road edges) of a site's Lanelet2 map: the vehicle lanes' directed centrelines f64[R, 2],
    their polygons as `Area`s of kind "lane", and its curbs, road borders and guard rails f64[P, 2]
    (`lanelet2.ROAD_BORDER_TYPES`; local frame of the track files)."""
    from gpd_jax.data.sources import lanelet2

    m = lanelet2.read_lanelet2(path, MAP_ORIGIN)
    if stats is not None:
        for k, v in m.counts.items():
            stats[f"map_{k}"] += v
    if not m.vehicle_lanelets:
        raise DataError(path, f"holds no vehicle lanelet (subtypes {', '.join(lanelet2.VEHICLE_SUBTYPES)})")
    areas = tuple(Area(AREA_KIND_ID["lane"], ring) for ring in m.vehicle_rings())
    return m.vehicle_centrelines(), areas, m.road_borders


def with_map(raw: RawLog, lanes: tuple, areas: tuple, road_edges: tuple = ()) -> RawLog:
    """The log with its site's lanes, drivable areas and road edges."""
    return dataclasses.replace(raw, lanes=tuple(lanes), areas=tuple(areas), road_edges=tuple(road_edges))


def read_log(track_file: TrackFile, db: str, stats: Counter | None = None) -> RawLog:
    """A track file with its site's map -> RawLog (`read_tracks`, `map_features`)."""
    return with_map(read_tracks(track_file.path, track_file.site, stats), *map_features(
        map_path(db, track_file.site), stats))


# ----------------------------------------------------------------------------------------------------- windows
def choose_windows(raw: RawLog, cfg: preprocess.SampleConfig = preprocess.SampleConfig(), seed: int = 0,
                   stride: int = WINDOW_STRIDE, min_travel: float = MIN_EGO_TRAVEL,
                   stats: Counter | None = None) -> list[tuple[int, int]]:
    """(start frame, ego track) of each window of a log: starts every `stride` frames; the ego drawn uniformly among
    the tracks valid in all `cfg.num_frames` frames whose centre moves at least `min_travel` metres from the first
    to the last frame, seeded by (seed, the log's name, start). Windows without such a track are counted
    (`skip_no_ego_candidate`) and left out."""
    T, F = cfg.num_frames, raw.num_frames
    if F < T:
        if stats is not None:
            stats["skip_log_too_short"] += 1
        return []
    cv = np.concatenate([np.zeros((1, raw.num_agents), np.int64), np.cumsum(raw.agent_valid, 0)], 0)
    name_key = zlib.crc32(raw.name.encode())
    out = []
    for s in range(0, F - T + 1, stride):
        cand = np.nonzero((cv[s + T] - cv[s]) == T)[0]
        travel = np.linalg.norm(raw.agent_xy[s + T - 1, cand] - raw.agent_xy[s, cand], axis=-1)
        cand = cand[travel >= min_travel]
        if len(cand) == 0:
            if stats is not None:
                stats["skip_no_ego_candidate"] += 1
            continue
        rng = np.random.default_rng([seed, name_key, s])
        out.append((s, int(cand[rng.integers(len(cand))])))
    return out


def log_samples(raw: RawLog, cfg: preprocess.SampleConfig, seed: int = 0, max_per_log: int | None = None,
                stats: Counter | None = None) -> list[tuple[str, dict]]:
    """(scenario id `<site>/<file>/<start>/<ego track id>`, sample) pairs of a log (`choose_windows`, then at most
    `max_per_log` windows drawn at random, seeded, then `preprocess.make_sample`)."""
    stats = Counter() if stats is None else stats
    preprocess.check_rawlog(raw)
    wins = choose_windows(raw, cfg, seed, stats=stats)
    if max_per_log is not None and len(wins) > max_per_log:
        stats["windows_over_max_per_log"] += len(wins) - max_per_log
        pick = np.sort(np.random.default_rng([seed, zlib.crc32(raw.name.encode()), 1]).choice(
            len(wins), max_per_log, replace=False))
        wins = [wins[i] for i in pick]
    lp = preprocess.lane_points(raw.lanes, cfg.lane_spacing)
    road = preprocess.road_index(raw, cfg)
    out = []
    for s, ego in wins:
        smp = preprocess.make_sample(raw, s, ego, cfg, lp, stats, road)
        if smp is not None:
            out.append((f"{raw.name}/{s}/{raw.agent_ids[ego]}", smp))
    return out


# ------------------------------------------------------------------------------------------------------- build
@dataclasses.dataclass(frozen=True)
class InteractionJob:
    """One track file, one shard: `index`, `split`, `site`, `path` (the CSV), `map` (the site's .osm)."""

    index: int
    split: str
    site: str
    path: str
    map: str
    num_samples: int = 1  # what run_jobs counts on its progress bar: files


def site_splits(sites, split: str | None) -> dict[str, str]:
    """Site -> split: `split` for every site when given (a known site put elsewhere is warned about), else
    `SITE_SPLITS`; a site it does not list is a `DataError` asking for `--split`."""
    out = {}
    for s in sites:
        known = SITE_SPLITS.get(s)
        if split is not None:
            if known is not None and known != split:
                log.warning("site %s belongs to the %s split (SITE_SPLITS) but is built into %s", s, known, split)
            out[s] = split
        elif known is None:
            raise DataError(None, f"site {s!r} is not in the fixed INTERACTION split (SITE_SPLITS): give --split")
        else:
            out[s] = known
    return out


def run_interaction_job(job: InteractionJob, out_dir: str, sample_cfg: preprocess.SampleConfig, seed: int = 0,
                        max_per_log: int | None = None) -> dict:
    """Reads the job's track file and map, cuts its windows and writes one shard. Returns the job summary; a bad
    file gives `error` = [path, reason] and no job marker (the job reruns)."""
    t0 = time.time()
    stats: Counter = Counter()
    try:
        raw = with_map(read_tracks(job.path, job.site, stats), *map_features(job.map, stats))
        pairs = log_samples(raw, sample_cfg, seed, max_per_log, stats)
    except DataError as e:
        return {"index": job.index, "split": job.split, "num_samples": 0, "requested": 1, "stats": {},
                "rejections": [], "error": [e.path, e.reason]}
    stats["files_read"] += 1
    stats["frames"] += raw.num_frames
    if pairs:
        arrays = store.stack_samples([p[1] for p in pairs], preprocess.sample_spec(sample_cfg))
        for sp in store.list_splits(out_dir):  # a shard of an interrupted earlier attempt
            shutil.rmtree(store.shard_dir(out_dir, sp, job.index), ignore_errors=True)
        store.write_shard(out_dir, job.split, job.index, arrays, [p[0] for p in pairs], [job.site] * len(pairs),
                          extra={"source": "interaction", "site": job.site})
    summary = {"index": job.index, "split": job.split, "site": job.site, "num_samples": len(pairs), "requested": 1,
               "wall_s": time.time() - t0, "stats": dict(stats), "rejections": []}
    store.atomic_write_json(job_marker(out_dir, job.index), summary)
    return summary


class _Bound:
    """Picklable job runner bound to its settings."""

    def __init__(self, out_dir, sample_cfg, seed, max_per_log):
        self.args = (out_dir, sample_cfg, seed, max_per_log)

    def __call__(self, job):
        return run_interaction_job(job, *self.args)


def build_interaction(out_dir: str, db: str, seed: int = 0, split: str | None = None, sites=None,
                      max_per_log: int | None = None, workers: int = 1,
                      sample_cfg: preprocess.SampleConfig | None = None, executor=None) -> dict:
    """Builds (or resumes) a store from INTERACTION track files and maps (one job and shard per track file).

    Args:
      out_dir: the store to write.
      db: the dataset root (`recorded_trackfiles/`, `maps/`).
      seed: ego choice and `max_per_log` draws.
      split: without `sites`, build the sites `SITE_SPLITS` puts into this split; with `sites`, put them all into it.
      sites: site names (default: all with track files, or those of `split`).
      max_per_log: at most this many windows per track file (default: every `WINDOW_STRIDE` frames).
      workers: processes.
      executor: where the jobs run (`gpd_jax.data.executors`; default: `workers` local processes).
    Raises `DataError` (naming the file) for a bad input file or an unknown site or map, and when `out_dir` holds a
    build with other settings.
    """
    t0 = time.time()
    sample_cfg = sample_cfg or preprocess.SampleConfig()
    db = os.fspath(db)
    if sites is None:
        have = list_sites(db)
        sites = [s for s in have if split is None or SITE_SPLITS.get(s) == split]
        if not sites:
            raise DataError(db, f"no site with track files belongs to the {split} split (SITE_SPLITS; sites with "
                                f"tracks: {', '.join(have) or 'none'})")
    sites = sorted(set(sites))
    files = find_track_files(db, sites)
    split_of = site_splits(sites, split)
    h = hashlib.sha256()
    for f in files:
        h.update(f"{f.key}\0{os.path.getsize(f.path)}\n".encode())
    for s in sites:
        h.update(f"{s}.osm\0{os.path.getsize(map_path(db, s))}\n".encode())
    os.makedirs(out_dir, exist_ok=True)
    store.clean_temporaries(out_dir)
    settings = {"source": "interaction", "db": os.path.abspath(db), "seed": seed, "split": split, "sites": sites,
                "site_splits": split_of, "max_per_log": max_per_log, "window_stride": WINDOW_STRIDE,
                "min_ego_travel": MIN_EGO_TRAVEL, "num_files": len(files), "files_sha256": h.hexdigest(),
                "sample_config": dataclasses.asdict(sample_cfg)}
    check_settings(out_dir, settings)
    jobs = [InteractionJob(i, split_of[f.site], f.site, f.path, map_path(db, f.site)) for i, f in enumerate(files)]
    results = run_jobs(jobs, _Bound(out_dir, sample_cfg, seed, max_per_log), out_dir, workers, "interaction build", executor)
    failed = [r for r in results if r.get("error")]
    if failed:
        raise DataError(*failed[0]["error"])
    per_site: dict = {}
    for r in results:
        e = per_site.setdefault(r["site"], {"split": r["split"], "files": 0, "samples": 0, "frames": 0})
        e["files"] += 1
        e["samples"] += r["num_samples"]
        e["frames"] += r["stats"].get("frames", 0)
    for e in per_site.values():
        e["hours"] = round(e.pop("frames") / 36000.0, 3)
    return finish(out_dir, settings, results, time.time() - t0, {"sites": per_site})
