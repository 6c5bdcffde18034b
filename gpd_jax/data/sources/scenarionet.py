"""The ScenarioNet importer: scenario `.pkl` files (Waymo, nuScenes, nuPlan, Argoverse 2, ... converted by
ScenarioNet) -> `RawLog` -> a store (`build_scenarionet`, with the shared job runner `gpd_jax.data.jobs`).

Input (`find_scenarios`): a ScenarioNet dataset directory (`dataset_summary.pkl`, whose keys are the scenario
file names and whose values are their metadata, plus the optional `dataset_mapping.pkl`, file name -> folder
relative to the dataset directory, which may point into sub-directories or sibling datasets after a merge), a
plain folder searched recursively for scenario `.pkl` files, or one scenario file. Every pickle - the summary and
the mapping too - is read with `gpd_jax.data.safe_pickle`, which refuses any global other than plain containers
and numpy arrays before it could run (pickles execute code on load).

A scenario is the dict of MetaDrive's `ScenarioDescription` (`metadrive/scenario/scenario_description.py`):
`tracks` (object id -> {`type`, `state`: per-frame arrays, `metadata`}), `map_features` (feature id ->
{`type`, `polyline`, optional `polygon`, ...}), `dynamic_map_states` (traffic lights), `metadata` (`ts`,
`sdc_id`, `dataset`, `scenario_id`, `coordinate`, and for some datasets `map`), `length`, `id`, `version`.

What is read, and the conventions:

* **Frames.** `metadata["ts"]` (seconds, one per frame; `length` frames) gives the frame period: the median
  step. 10 Hz (a step within `PERIOD_TOLERANCE` of 0.1 s) is taken as is; an integer multiple of 10 Hz (20 Hz,
  30 Hz, ...) is resampled to 10 Hz by keeping every k-th frame from frame 0 (no interpolation, so validity
  stays exact); any other rate (2 Hz, 15 Hz, ...) is refused with a `DataError` that names the file and the
  rate. A step that differs from the median by more than `PERIOD_TOLERANCE` (a dropped or repeated frame) is a
  `DataError` too: the frame index must be the time. `RawLog.timestamps` are the kept `ts` from the first.
* **Coordinates.** Positions are metres in the scenario's world frame; `state["position"]` is (T, 2) or (T, 3)
  (z is dropped); converters may centre it on the ego's first pose (nuPlan), which is harmless since only
  relative geometry is used. Headings are radians counter-clockwise from +x. The `metadata["coordinate"]` tags
  ("waymo", "metadrive", nuPlan's "right-handed") are all right-handed in current MetaDrive ("all coordinates
  is right-handed now"); files from MetaDrive < 0.3 tagged "metadrive" had y mirrored, so the tag is not
  trusted. A frame mirrored as a whole (positions and headings alike) cannot be told from the data; headings
  that do not belong to the positions' frame (one of them mirrored, degrees, another zero direction) can: a
  scenario whose ego heading disagrees with its direction of motion by more than 90 degrees in the median over
  frames where it moves faster than 2 m/s is refused (`DataError`).
* **Ego.** The track named by `metadata["sdc_id"]` (`RawLog.ego_index`), whatever its type. No `sdc_id`, or
  one that names no track, is a `DataError`. The build (`build_scenarionet`) cuts windows every
  `SampleConfig.window_stride` frames in which the ego is valid throughout (others are counted as
  `skip_ego_not_present`), keeps at most `--max-per-log` of them, and makes the samples with
  `gpd_jax.data.preprocess.make_sample`.
* **Agents.** Tracks of type `VEHICLE` are kept. `gpd_jax.scene.AGENT_TYPES` has vehicle classes only (GPD-1
  models vehicles), so `PEDESTRIAN`, `CYCLIST` and every other type (`OTHER`, traffic cones and barriers, ...)
  are **dropped and counted** (`tracks_dropped_<type>` in the build statistics), as the nuPlan source drops
  pedestrians and bicycles. Tracks never valid (after resampling) are dropped and counted too.
  `agent_valid` is `state["valid"]`; positions and headings of invalid frames are NaN in the RawLog.
* **Sizes and vehicle classes.** (length, width) per track is the median of `state["length"]` and
  `state["width"]` over its valid frames (arrays of T or (T, 1)). A track without them, or with non-positive
  values, gets `DEFAULT_SIZE` and is counted (`agent_size_defaulted`). ScenarioNet has one `VEHICLE` type, so
  the class comes from the length as for nuPlan (`gpd_jax.data.sources.nuplan.vehicle_type`: car < 6.5 m <=
  truck < 10 m <= bus).
* **Lanes.** The centrelines are the `polyline`s of the map features whose type is a vehicle lane:
  `LANE_SURFACE_STREET`, `LANE_FREEWAY`, `LANE_SURFACE_UNSTRUCTURE`, `LANE_UNKNOWN` (`VEHICLE_LANE_TYPES`).
  `LANE_BIKE_LANE` is not a vehicle lane and is left out (counted). Road lines (`ROAD_LINE_*`), road edges
  (`ROAD_EDGE_*`), crosswalks, speed bumps and stop signs are counted by kind
  (`map_<kind>` statistics); of them only the road edges are used (below).
* **Traffic lights** (`RawLog.signals`): each `dynamic_map_states` entry of type `TRAFFIC_LIGHT` with a `lane`
  that is a vehicle lane of the map and a `stop_point`: its states per frame (`state["object_state"]`, Waymo's
  `LANE_STATE_*` or MetaDrive's `TRAFFIC_LIGHT_RED|YELLOW|GREEN|UNKNOWN`, `light_state`), resampled with the
  frames. Others are counted (`signals_without_lane_or_stop`).
* **Drivable area** (`RawLog.areas`): each vehicle lane's `polygon` where it encloses an area (nuPlan and
  nuScenes conversions), else its centreline buffered by its `width` ((P, 2): distances to the left and right
  boundaries; (P,) or a scalar: the full width), else by `DEFAULT_LANE_WIDTH` (counted:
  `lane_width_defaulted`); `DRIVEWAY` polygons as "other" drivable area. The road edges of a sample are the
  boundary of that union (`gpd_jax.data.roadgeom`). ScenarioNet has no junction feature: junction areas are
  what the lanes crossing them cover (kind "lane").
* **Map road edges** (`RawLog.road_edges`, what the realism metric reads): the `ROAD_EDGE_*` polylines (Waymo's
  conversions; they bound the road with shoulders and kerbs the lanes do not cover), oriented against the
  areas' union; a scenario without them (nuScenes conversions: lanes and road lines only) gets the outline of
  the lane union, tagged "lane_union" (`gpd_jax.geometry.EDGE_SOURCES`).
* **Location** (`scenario_location`, the key splits are made by): the first of `metadata["map"]`,
  `["location"]`, `["city"]`, `["map_name"]` that is set (for nuScenes and nuPlan the map name, so the same road
  network gets the same key as from the nuPlan source). Waymo scenarios name no map: each is its own location
  (`<dataset>:<scenario_id>`), so splits by location cannot keep Waymo roads apart; build Waymo's own
  training / validation / testing sets separately with `--split`.
* `RawLog.name` is the file name without `.pkl`.

Every problem with an input file raises `gpd_jax.data.errors.DataError` naming the file and the reason: an
unreadable, truncated or corrupt pickle, a pickle naming a foreign class, a missing key (the path of the key is
named), array lengths that disagree with `ts`, a missing sdc, an unsupported frame rate.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import shutil
import time
import warnings
from collections import Counter
from typing import Any, Iterable, Iterator

import numpy as np

from gpd_jax.data import preprocess, safe_pickle, store
from gpd_jax.data.boxes import sample_has_overlap
from gpd_jax.data.errors import DataError
from gpd_jax.data.jobs import assign_splits, check_settings, finish, job_marker, run_jobs
from gpd_jax.data.raw import RawLog
from gpd_jax.data.roadgeom import Area, lane_area
from gpd_jax.data.signals import RawSignals
from gpd_jax.geometry import AREA_KIND_ID, SIGNAL_STATE_ID
from gpd_jax.scene import TYPE_ID

log = logging.getLogger(__name__)

SUMMARY_FILE = "dataset_summary.pkl"
MAPPING_FILE = "dataset_mapping.pkl"

TARGET_PERIOD = 0.1  # seconds (10 Hz)
PERIOD_TOLERANCE = 0.2  # relative: a step may differ from the median by 20 %, the median from k * 0.1 s by 2 %
RATE_TOLERANCE = 0.02

VEHICLE_TYPE = "VEHICLE"
DEFAULT_LANE_WIDTH = 3.5  # metres, for a lane with neither a polygon nor a width
VEHICLE_LANE_TYPES = ("LANE_SURFACE_STREET", "LANE_FREEWAY", "LANE_SURFACE_UNSTRUCTURE", "LANE_UNKNOWN")
LOCATION_KEYS = ("map", "location", "city", "map_name")
DEFAULT_SIZE = (4.6, 1.85)  # metres, a mid-size car, for tracks without length / width

HEADING_CHECK_SPEED = 2.0  # m/s
HEADING_CHECK_MIN_FRAMES = 10


@dataclasses.dataclass(frozen=True)
class ScenarioFile:
    """One scenario file of a dataset.

    Attributes:
      path: the file's path.
      key: its name relative to the dataset (the summary key, or the path below a plain folder).
      metadata: its `metadata` dict from `dataset_summary.pkl`, or None when there is no summary.
    """

    path: str
    key: str
    metadata: dict | None = None


# ---------------------------------------------------------------------------------------------------------
# Finding scenario files
# ---------------------------------------------------------------------------------------------------------


def _is_scenario_name(name: str) -> bool:
    return name.endswith(".pkl") and name not in (SUMMARY_FILE, MAPPING_FILE)


def find_scenarios(db: str | os.PathLike) -> list[ScenarioFile]:
    """The scenario files of a dataset directory, a plain folder, or a single `.pkl` file (sorted by key).

    Raises `DataError` when `db` does not exist, holds no scenario file, or its summary lists a file that is
    missing (or the summary / mapping cannot be read safely).
    """
    db = os.fspath(db)
    if os.path.isfile(db):
        if not db.endswith(".pkl") or os.path.basename(db) in (SUMMARY_FILE, MAPPING_FILE):
            raise DataError(db, "not a scenario .pkl file (give the dataset directory for a summary file)")
        return [ScenarioFile(db, os.path.basename(db))]
    if not os.path.isdir(db):
        raise DataError(db, "no such file or directory")
    summary_path = os.path.join(db, SUMMARY_FILE)
    if os.path.isfile(summary_path):
        summary = safe_pickle.load(summary_path)
        if not isinstance(summary, dict):
            raise DataError(summary_path, f"expected a dict of file name -> metadata, got {type(summary).__name__}")
        mapping_path = os.path.join(db, MAPPING_FILE)
        mapping = safe_pickle.load(mapping_path) if os.path.isfile(mapping_path) else {}
        if not isinstance(mapping, dict):
            raise DataError(mapping_path, f"expected a dict of file name -> folder, got {type(mapping).__name__}")
        out = []
        for key in sorted(summary, key=str):
            name = str(key)
            sub = mapping.get(key, "") or ""
            if not isinstance(sub, str):
                raise DataError(mapping_path, f"entry {name!r}: folder is a {type(sub).__name__}, not a string")
            path = os.path.normpath(os.path.join(db, sub, name))
            if not os.path.isfile(path):
                raise DataError(path, f"listed in {summary_path} but missing")
            meta = summary[key] if isinstance(summary[key], dict) else None
            out.append(ScenarioFile(path, os.path.join(sub, name) if sub else name, meta))
        if not out:
            raise DataError(summary_path, "the dataset summary lists no scenario")
        return out
    out = []
    for root, dirs, files in os.walk(db):
        dirs.sort()
        for name in sorted(files):
            if _is_scenario_name(name):
                path = os.path.join(root, name)
                out.append(ScenarioFile(path, os.path.relpath(path, db)))
    if not out:
        raise DataError(db, f"no scenario .pkl files (and no {SUMMARY_FILE})")
    return sorted(out, key=lambda f: f.key)


def scenario_location(metadata: dict | None, fallback: str) -> str:
    """The split key of a scenario from its metadata (see the module docstring); `fallback` (normally the file
    stem) stands in for a missing `scenario_id`."""
    md = metadata if isinstance(metadata, dict) else {}
    for k in LOCATION_KEYS:
        v = md.get(k)
        if isinstance(v, (str, bytes)) and str(v).strip():
            return str(v).strip()
    dataset = str(md.get("dataset") or "scenarionet")
    sid = md.get("scenario_id") or md.get("id") or fallback
    return f"{dataset}:{sid}"


def scenario_dataset(metadata: dict | None) -> str:
    """The `metadata["dataset"]` name ("waymo", "nuscenes", ...), or "unknown"."""
    md = metadata if isinstance(metadata, dict) else {}
    v = md.get("dataset")
    return str(v) if v else "unknown"


# ---------------------------------------------------------------------------------------------------------
# One scenario -> RawLog
# ---------------------------------------------------------------------------------------------------------


def file_stem(path: str) -> str:
    """The file name without `.pkl` (`RawLog.name`)."""
    base = os.path.basename(path)
    return base[:-4] if base.endswith(".pkl") else base


def _need(d: Any, key: str, where: str, path: str) -> Any:
    if not isinstance(d, dict):
        raise DataError(path, f"{where} is a {type(d).__name__}, expected a dict")
    if key not in d:
        raise DataError(path, f"missing key {where}[{key!r}]")
    return d[key]


def frame_step(ts: np.ndarray, path: str) -> int:
    """How many source frames make one 10 Hz frame (1 for 10 Hz, 2 for 20 Hz, ...) from timestamps f[T].

    Raises `DataError` (naming `path` and the rate) for non-increasing or irregular timestamps and for rates that
    are not an integer multiple of 10 Hz.
    """
    ts = np.asarray(ts, np.float64)
    if ts.ndim != 1 or len(ts) < 2:
        raise DataError(path, f"metadata['ts'] has shape {ts.shape}: need at least 2 timestamps")
    if not np.isfinite(ts).all():
        raise DataError(path, "metadata['ts'] has non-finite timestamps")
    steps = np.diff(ts)
    period = float(np.median(steps))
    if not period > 0:
        raise DataError(path, f"metadata['ts'] is not increasing (median step {period} s)")
    bad = np.nonzero(np.abs(steps - period) > PERIOD_TOLERANCE * period)[0]
    if len(bad):
        i = int(bad[0])
        raise DataError(path, f"irregular timestamps: step {steps[i]:.4f} s between frames {i} and {i + 1} "
                              f"(period {period:.4f} s; {len(bad)} such steps): a dropped or repeated frame")
    k = int(round(TARGET_PERIOD / period))
    if k < 1 or abs(k * period - TARGET_PERIOD) > RATE_TOLERANCE * TARGET_PERIOD:
        raise DataError(path, f"frame period {period:.4f} s ({1.0 / period:.2f} Hz) is not 10 Hz or an integer "
                              "multiple of it; only those rates are read (higher multiples are resampled to 10 Hz "
                              "by keeping every k-th frame)")
    return k


def _per_frame(arr, T: int, name: str, where: str, path: str, cols: tuple[int, ...] = (1,)) -> np.ndarray:
    """State array -> f64[T] (cols (1,)) or f64[T, c] (c in cols), with a DataError naming the key otherwise."""
    try:
        a = np.asarray(arr, np.float64)
    except (TypeError, ValueError) as e:
        raise DataError(path, f"{where}[{name!r}] is not numeric: {e}") from None
    if a.ndim == 2 and a.shape[1] == 1 and cols == (1,):
        a = a[:, 0]
    ok = (a.ndim == 1 and cols == (1,)) or (a.ndim == 2 and a.shape[1] in cols)
    if not ok or a.shape[0] != T:
        want = f"({T},)" if cols == (1,) else " or ".join(f"({T}, {c})" for c in cols)
        raise DataError(path, f"{where}[{name!r}] has shape {a.shape}, expected {want} (one entry per frame "
                              "of metadata['ts'])")
    return a


def _map_kind(t: str) -> str:
    if t in VEHICLE_LANE_TYPES:
        return "lane"
    if t.startswith("LANE_"):
        return "lane_other"  # LANE_BIKE_LANE
    if t.startswith("ROAD_EDGE"):
        return "road_edge"
    if t.startswith("ROAD_LINE") or t == "UNKNOWN_LINE":
        return "road_line"
    return t.lower() if t in ("CROSSWALK", "SPEED_BUMP", "DRIVEWAY", "STOP_SIGN") else "other"


def scenario_to_rawlog(scenario: Any, path: str, location: str | None = None,
                       stats: Counter | None = None) -> RawLog:
    """A ScenarioNet scenario dict (read from `path`, named in errors) -> RawLog (conventions: module docstring).

    Args:
      scenario: the unpickled scenario.
      path: its file (for error messages and `RawLog.name`).
      location: the split key; by default `scenario_location(metadata, file stem)`.
      stats: a Counter that receives track, map and resampling counts.
    """
    path = os.fspath(path)
    stats = Counter() if stats is None else stats
    if not isinstance(scenario, dict):
        raise DataError(path, f"not a ScenarioNet scenario: the pickle holds a {type(scenario).__name__}, "
                              "expected a dict")
    tracks = _need(scenario, "tracks", "scenario", path)
    map_features = _need(scenario, "map_features", "scenario", path)
    md = _need(scenario, "metadata", "scenario", path)
    ts = _need(md, "ts", "scenario['metadata']", path)
    sdc = _need(md, "sdc_id", "scenario['metadata']", path)
    if not isinstance(tracks, dict):
        raise DataError(path, f"scenario['tracks'] is a {type(tracks).__name__}, expected a dict")
    if not isinstance(map_features, dict):
        raise DataError(path, f"scenario['map_features'] is a {type(map_features).__name__}, expected a dict")
    try:
        ts = np.asarray(ts, np.float64)
    except (TypeError, ValueError) as e:
        raise DataError(path, f"metadata['ts'] is not numeric: {e}") from None
    k = frame_step(ts, path)
    T = int(ts.shape[0])
    length = scenario.get("length", T)
    if not isinstance(length, (int, np.integer)) or int(length) != T:
        raise DataError(path, f"scenario['length'] = {length!r} but metadata['ts'] has {T} entries")
    if k > 1:
        stats["scenarios_resampled_to_10hz"] += 1
    keep = slice(0, T, k)
    ids = {str(key): key for key in tracks}
    if sdc is None or str(sdc) not in ids:
        raise DataError(path, f"metadata['sdc_id'] = {sdc!r} names no track ({len(tracks)} tracks): no ego")
    sdc = str(sdc)
    names, xys, heads, valids, lengths, widths, types = [], [], [], [], [], [], []
    nan_frames = np.full(len(range(0, T, k)), np.nan)
    for sid in [sdc] + sorted((i for i in ids if i != sdc), key=_track_order):
        tr = tracks[ids[sid]]
        where = f"scenario['tracks'][{sid!r}]"
        ttype = str(_need(tr, "type", where, path)).upper()
        if sid != sdc and ttype != VEHICLE_TYPE:
            stats[f"tracks_dropped_{ttype.lower()}"] += 1
            continue
        st = _need(tr, "state", where, path)
        sw = where + "['state']"
        pos = _per_frame(_need(st, "position", sw, path), T, "position", sw, path, cols=(2, 3))[:, :2]
        hd = _per_frame(_need(st, "heading", sw, path), T, "heading", sw, path)
        vd = np.asarray(_need(st, "valid", sw, path))
        if vd.shape not in ((T,), (T, 1)):
            raise DataError(path, f"{sw}['valid'] has shape {vd.shape}, expected ({T},)")
        vd = vd.reshape(T).astype(bool)
        pos, hd, vd = pos[keep], hd[keep], vd[keep]
        if not vd.any():
            if sid == sdc:
                raise DataError(path, f"the ego track {sdc!r} (metadata['sdc_id']) is never valid")
            stats["tracks_dropped_never_valid"] += 1
            continue
        if "length" in st and "width" in st:
            lengths.append(_per_frame(st["length"], T, "length", sw, path)[keep])
            widths.append(_per_frame(st["width"], T, "width", sw, path)[keep])
        else:
            lengths.append(nan_frames)
            widths.append(nan_frames)
        names.append(sid)
        xys.append(pos)
        heads.append(hd)
        valids.append(vd)
        types.append(ttype)
    stats["tracks_vehicle"] += len(names) - 1
    valid = np.stack(valids, 1)  # [F, N]
    xy = np.stack(xys, 1)
    xy[~valid] = np.nan
    heading = np.stack(heads, 1)
    heading[~valid] = np.nan
    size_frames = np.stack([np.stack(lengths, 1), np.stack(widths, 1)], -1)  # [F, N, 2]
    size_frames[~valid] = np.nan
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN columns: tracks without sizes
        size_arr = np.nanmedian(size_frames, axis=0)  # [N, 2] over valid frames
    bad = ~(np.isfinite(size_arr) & (size_arr > 0)).all(-1)
    size_arr[bad] = DEFAULT_SIZE
    stats["agent_size_defaulted"] += int(bad.sum())
    size_arr = size_arr.astype(np.float32)
    lanes, areas, edges, lane_lines = [], [], [], {}
    for fid in sorted(map_features, key=_track_order):
        feat = map_features[fid]
        ftype = str(_need(feat, "type", f"scenario['map_features'][{str(fid)!r}]", path)).upper()
        kind = _map_kind(ftype)
        stats[f"map_{kind}"] += 1
        fw = f"scenario['map_features'][{str(fid)!r}]"
        if kind == "driveway":
            ring = _polygon_of(feat, fw, path)
            if ring is not None:
                areas.append(Area(AREA_KIND_ID["other"], ring))
        if kind == "road_edge":
            edge = _finite_points(_need(feat, "polyline", fw, path), "polyline", "P", fw, path)
            if len(edge) >= 2:
                edges.append(edge)
        if kind != "lane":
            continue
        if "polygon" in feat:
            stats["map_lane_with_polygon"] += 1
        if "width" in feat:
            stats["map_lane_with_width"] += 1
        pl = _finite_points(_need(feat, "polyline", fw, path), "polyline", "P", fw, path)
        if len(pl) < 2:
            stats["lane_polylines_too_short"] += 1
            continue
        lanes.append(pl)
        lane_lines[str(fid)] = pl
        area = _lane_area(feat, pl, fw, path, stats)
        if area is not None:
            areas.append(area)
    from gpd_jax.data.sources.nuplan import vehicle_type

    atype = vehicle_type(size_arr[:, 0]).astype(np.int32)
    atype[0] = TYPE_ID["ego"]
    _check_ego_heading(xy[:, 0], heading[:, 0], valid[:, 0], k * float(np.median(np.diff(ts))), path)
    tk = ts[keep]
    return RawLog(name=file_stem(path), location=location or scenario_location(md, file_stem(path)),
                  timestamps=tk - tk[0], agent_ids=tuple(names), agent_xy=xy, agent_heading=heading,
                  agent_valid=valid, agent_size=size_arr, agent_type=atype, lanes=tuple(lanes), ego_index=0,
                  areas=tuple(areas), road_edges=tuple(edges),
                  signals=_signals(scenario.get("dynamic_map_states"), lane_lines, T, keep, path, stats))


# ScenarioNet's traffic-light state strings -> WOSAC lane states (`gpd_jax.geometry.SIGNAL_STATES`): Waymo's
# `LANE_STATE_*` names as they are, MetaDrive's `TRAFFIC_LIGHT_*` (nuPlan and other conversions) by colour.
_LIGHT_COLOURS = {"RED": "stop", "YELLOW": "caution", "GREEN": "go", "UNKNOWN": "unknown"}


def light_state(value) -> int:
    """One frame's traffic-light state string (or None) -> index into `SIGNAL_STATES` (0 for what is unknown)."""
    if value is None:
        return 0
    v = str(value).upper()
    if v.startswith("LANE_STATE_"):
        return SIGNAL_STATE_ID.get(v[len("LANE_STATE_"):].lower(), 0)
    if v.startswith("TRAFFIC_LIGHT_"):
        return SIGNAL_STATE_ID[_LIGHT_COLOURS.get(v[len("TRAFFIC_LIGHT_"):], "unknown")]
    return 0


def _signals(states, lane_lines: dict, T: int, keep: slice, path: str, stats: Counter) -> RawSignals | None:
    """`dynamic_map_states` -> `RawSignals` (None without traffic lights): per light its `stop_point`, the
    centreline of its `lane` (a vehicle lane of the map) and its `state["object_state"]` per frame. A light
    whose lane is not a vehicle lane of the map, or without a stop point, is left out (counted)."""
    if not isinstance(states, dict) or not states:
        return None
    stops, lines, cols = [], [], []
    for sid in sorted(states, key=_track_order):
        st = states[sid]
        where = f"scenario['dynamic_map_states'][{str(sid)!r}]"
        if not isinstance(st, dict) or str(st.get("type", "TRAFFIC_LIGHT")).upper() != "TRAFFIC_LIGHT":
            continue
        lane, stop = lane_lines.get(str(st.get("lane"))), st.get("stop_point")
        seq = (st.get("state") or {}).get("object_state") if isinstance(st.get("state"), dict) else None
        if lane is None or stop is None or seq is None:
            stats["signals_without_lane_or_stop"] += 1
            continue
        stop = np.asarray(stop, np.float64).reshape(-1)[:2]
        if stop.shape != (2,) or not np.isfinite(stop).all():
            raise DataError(path, f"{where}['stop_point'] is not a point: {st.get('stop_point')!r}")
        if len(seq) != T:
            raise DataError(path, f"{where}['state']['object_state'] has {len(seq)} entries, expected {T}")
        stops.append(stop)
        lines.append(lane)
        cols.append([light_state(v) for v in list(seq)[keep]])
    if not cols:
        return None
    stats["signals"] += len(cols)
    return RawSignals(stop=np.stack(stops), lane=tuple(lines), state=np.asarray(cols, np.int8).T)


def _finite_points(value, key: str, n: str, fw: str, path: str) -> np.ndarray:
    """A feature's `key` ((n, 2) or (n, 3) numbers) as its finite xy points f64[<= n, 2]; DataError otherwise."""
    try:
        pts = np.asarray(value, np.float64)
    except (TypeError, ValueError) as e:
        raise DataError(path, f"{fw}['{key}'] is not numeric: {e}") from None
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise DataError(path, f"{fw}['{key}'] has shape {pts.shape}, expected ({n}, 2) or ({n}, 3)")
    pts = pts[:, :2]
    return pts[np.isfinite(pts).all(-1)]


def _polygon_of(feat: dict, fw: str, path: str) -> np.ndarray | None:
    """The feature's `polygon` as f64[Q, 2] if it encloses an area (>= 3 finite points, area > 0.5 m^2)."""
    if "polygon" not in feat or feat["polygon"] is None:
        return None
    pg = _finite_points(feat["polygon"], "polygon", "Q", fw, path)
    if len(pg) < 3:
        return None
    x, y = pg[:, 0], pg[:, 1]
    area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    return pg if area > 0.5 else None


def _lane_area(feat: dict, pl: np.ndarray, fw: str, path: str, stats: Counter) -> Area | None:
    """A vehicle lane's drivable area: its `polygon` where it encloses an area, else its centreline `pl` buffered
    by `width` (per point: (P, 2) = distances to the left and right boundary, (P,) or (P, 1) or a scalar = the
    full width), else by `DEFAULT_LANE_WIDTH` (counted: `lane_width_defaulted`)."""
    ring = _polygon_of(feat, fw, path)
    if ring is not None:
        stats["lane_area_from_polygon"] += 1
        return Area(AREA_KIND_ID["lane"], ring)
    w = feat.get("width")
    if w is not None:
        try:
            w = np.asarray(w, np.float64)
        except (TypeError, ValueError):
            w = None
    if w is not None and w.ndim == 2 and w.shape == (len(pl), 2) and np.isfinite(w).all() and (w > 0).all():
        stats["lane_area_from_width"] += 1
        return lane_area(pl, w[:, 0] + w[:, 1], offset=(w[:, 0] - w[:, 1]) / 2)
    if w is not None and w.size in (1, len(pl)) and np.isfinite(w).all() and (w > 0).all():
        stats["lane_area_from_width"] += 1
        return lane_area(pl, w.reshape(-1) if w.size > 1 else float(w.reshape(-1)[0]))
    stats["lane_width_defaulted"] += 1
    return lane_area(pl, DEFAULT_LANE_WIDTH)


def _track_order(key) -> tuple:
    s = str(key)
    return (0, int(s), s) if s.isdigit() else (1, 0, s)


def _check_ego_heading(xy: np.ndarray, heading: np.ndarray, valid: np.ndarray, dt: float, path: str) -> None:
    """Refuses a scenario whose ego heading points away from its motion (mirrored frame, degrees, ...)."""
    ok = valid[1:] & valid[:-1]
    d = np.diff(xy, axis=0)
    speed = np.linalg.norm(d, axis=-1) / dt
    moving = ok & (speed > HEADING_CHECK_SPEED)
    if moving.sum() < HEADING_CHECK_MIN_FRAMES:
        return
    direction = np.arctan2(d[moving, 1], d[moving, 0])
    err = np.abs((heading[1:][moving] - direction + np.pi) % (2 * np.pi) - np.pi)
    med = float(np.median(err))
    if med > np.pi / 2:
        raise DataError(path, f"the ego's heading disagrees with its direction of motion by {np.degrees(med):.0f} "
                              "degrees (median over moving frames): headings are not radians counter-clockwise "
                              "from +x in the positions' frame (a mirrored, left-handed frame?)")


def read_scenario(path: str | os.PathLike, location: str | None = None, stats: Counter | None = None) -> RawLog:
    """Reads one scenario file safely (`safe_pickle.load`) -> RawLog. Raises `DataError` naming the file."""
    path = os.fspath(path)
    return scenario_to_rawlog(safe_pickle.load(path), path, location, stats)


def iter_scenarios(db: str | os.PathLike | Iterable[ScenarioFile], skip_bad: bool = False,
                   errors: list | None = None, stats: Counter | None = None) -> Iterator[RawLog]:
    """Yields a RawLog per scenario of `db` (see `find_scenarios`), in key order, reading one file at a time.

    With `skip_bad`, a file that raises `DataError` is skipped and the error appended to `errors`; otherwise
    the error propagates.
    """
    files = find_scenarios(db) if isinstance(db, (str, os.PathLike)) else list(db)
    for f in files:
        try:
            loc = None if f.metadata is None else scenario_location(f.metadata, file_stem(f.path))
            yield read_scenario(f.path, loc, stats)
        except DataError as e:
            if not skip_bad:
                raise
            if errors is not None:
                errors.append(e)


# ----------------------------------------------------------------------------------------------- build
@dataclasses.dataclass(frozen=True)
class ScenarioNetJob:
    """Scenario files of one split and one dataset ("waymo", "nuscenes", ...) that make one shard.

    `paths` and `locations` (the split key of each file) are parallel tuples; `num_samples` is the number of
    scenarios (what `run_jobs` counts on its progress bar)."""

    index: int
    split: str
    dataset: str
    paths: tuple[str, ...]
    locations: tuple[str, ...]

    @property
    def num_samples(self) -> int:
        return len(self.paths)


def _scenarionet_index(out_dir: str, files, fingerprint: str) -> list[tuple[str, str]]:
    """(location, dataset) of every scenario file: from `dataset_summary.pkl` where there is one, otherwise by
    reading each file once (cached in `_jobs/scenario_index.json`, so a resumed build does not read them again)."""
    from tqdm import tqdm

    if all(f.metadata is not None for f in files):
        return [(scenario_location(f.metadata, file_stem(f.path)), scenario_dataset(f.metadata)) for f in files]
    p = os.path.join(out_dir, "_jobs", "scenario_index.json")
    if os.path.isfile(p):
        with open(p) as fh:
            cached = json.load(fh)
        if cached.get("fingerprint") == fingerprint and len(cached.get("index", [])) == len(files):
            return [tuple(x) for x in cached["index"]]
    out = []
    for f in tqdm(files, desc="scenarionet index", unit="scn"):
        md = f.metadata
        if md is None:
            sc = safe_pickle.load(f.path)
            md = sc.get("metadata") if isinstance(sc, dict) else None
        out.append((scenario_location(md, file_stem(f.path)), scenario_dataset(md)))
    store.atomic_write_json(p, {"fingerprint": fingerprint, "index": out})
    return out


def _plan_scenarionet_jobs(paths: list[str], index: list[tuple[str, str]], seed: int, split: str | None,
                           per_job: int) -> list[ScenarioNetJob]:
    """Splits by location (`assign_splits`), then chunks of `per_job` files of one split and one dataset, in
    order of (split, dataset, location, path)."""
    locs = [loc for loc, _ in index]
    split_of = {loc: split for loc in locs} if split else assign_splits(locs, seed)
    rows = sorted(((split_of[loc], ds, loc, p) for p, (loc, ds) in zip(paths, index)))
    jobs: list[ScenarioNetJob] = []
    a = 0
    while a < len(rows):
        sp, ds = rows[a][0], rows[a][1]
        b = a
        while b < len(rows) and b - a < per_job and rows[b][:2] == (sp, ds):
            b += 1
        chunk = rows[a:b]
        jobs.append(ScenarioNetJob(len(jobs), sp, ds, tuple(r[3] for r in chunk), tuple(r[2] for r in chunk)))
        a = b
    return jobs


def _scenario_samples(raw, sample_cfg, max_per_log, seed, stats) -> list:
    """(scenario id, sample) pairs of a scenario (`raw.ego_index` set): the windows every `window_stride` frames
    in which the ego is present throughout, then at most `max_per_log` of them drawn at random (seeded) before
    any sample is made. (`preprocess.iter_samples(num=...)` draws among all starts before it knows which have
    the ego, which can leave none from a scenario whose ego is absent in some windows, and making every window
    first would cost `max_per_log`-fold.)"""
    preprocess.check_rawlog(raw)
    T, F, ego = sample_cfg.num_frames, raw.num_frames, int(raw.ego_index)
    if F < T:
        stats["skip_log_too_short"] += 1
        return []
    cv = np.concatenate([[0], np.cumsum(raw.agent_valid[:, ego])])
    starts = np.arange(0, F - T + 1, sample_cfg.window_stride)
    present = (cv[starts + T] - cv[starts]) == T
    stats["skip_ego_not_present"] += int((~present).sum())
    starts = starts[present]
    if max_per_log is not None and len(starts) > max_per_log:
        stats["windows_over_max_per_log"] += len(starts) - max_per_log
        starts = np.sort(np.random.default_rng([seed, len(starts)]).choice(starts, max_per_log, replace=False))
    lp = preprocess.lane_points(raw.lanes, sample_cfg.lane_spacing)
    road = preprocess.road_index(raw, sample_cfg)
    out = []
    for s in starts.tolist():
        smp = preprocess.make_sample(raw, s, ego, sample_cfg, lp, stats, road)
        if smp is None:
            continue
        if sample_cfg.reject_overlaps and sample_has_overlap(smp["xy"], smp["heading"], smp["valid"], smp["size"]):
            stats["skip_overlapping_boxes"] += 1
            stats["samples"] -= 1
            continue
        out.append((f"{raw.name}/{s}/{raw.agent_ids[ego]}", smp))
    return out


def run_scenarionet_job(job: ScenarioNetJob, out_dir: str, sample_cfg: preprocess.SampleConfig,
                        max_per_log: int | None = None, seed: int = 0, skip_bad: bool = False) -> dict:
    """Reads the job's scenario files (`read_scenario`), cuts their windows and writes one shard. Returns the job
    summary; a bad file (`DataError`) is skipped and counted with `skip_bad`, otherwise the summary carries
    `error` = [path, reason] and no job marker is written (the job reruns)."""
    t0 = time.time()
    stats: Counter = Counter()
    ids, samples, locs, rejections = [], [], [], []
    for path, loc in zip(job.paths, job.locations):
        try:
            raw = read_scenario(path, loc, stats)
            pairs = _scenario_samples(raw, sample_cfg, max_per_log, seed, stats)
        except DataError as e:
            if not skip_bad:
                return {"index": job.index, "split": job.split, "num_samples": 0, "requested": len(job.paths),
                        "stats": {}, "rejections": [], "error": [e.path, e.reason]}
            stats["scenarios_skipped_bad"] += 1
            rejections.append(str(e))
            continue
        stats["scenarios_read"] += 1
        stats["scenarios_without_samples"] += not pairs
        for sid, s in pairs:
            ids.append(sid)
            samples.append(s)
            locs.append(raw.location)
    if samples:
        arrays = store.stack_samples(samples, preprocess.sample_spec(sample_cfg))
        for sp in store.list_splits(out_dir):  # a shard of an interrupted earlier attempt
            shutil.rmtree(store.shard_dir(out_dir, sp, job.index), ignore_errors=True)
        store.write_shard(out_dir, job.split, job.index, arrays, ids, locs,
                          extra={"source": "scenarionet", "dataset": job.dataset})
    summary = {"index": job.index, "split": job.split, "dataset": job.dataset, "num_samples": len(samples),
               "requested": len(job.paths), "wall_s": time.time() - t0, "stats": dict(stats),
               "rejections": rejections}
    store.atomic_write_json(job_marker(out_dir, job.index), summary)
    return summary


class _ScenarioNetBound:
    """Picklable ScenarioNet job runner bound to its settings."""

    def __init__(self, out_dir, sample_cfg, max_per_log, seed, skip_bad):
        self.args = (out_dir, sample_cfg, max_per_log, seed, skip_bad)

    def __call__(self, job):
        return run_scenarionet_job(job, *self.args)


def build_scenarionet(out_dir: str, db: str, seed: int = 0, split: str | None = None,
                      max_per_log: int | None = None, workers: int = 1, per_job: int = 50,
                      skip_bad: bool = False, sample_cfg: preprocess.SampleConfig | None = None, executor=None) -> dict:
    """Builds (or resumes) a dataset from ScenarioNet scenarios (`find_scenarios`, `read_scenario`).

    Args:
      out_dir: the store to write.
      db: a ScenarioNet dataset directory, a plain folder of scenario `.pkl` files, or one file.
      seed: split assignment and window choice seed.
      split: put everything into this split (default: splits by location, see `scenario_location`).
      max_per_log: at most this many windows per scenario (default: every `window_stride` frames).
      workers: processes; per_job: scenario files per job (one shard each, of one split and one dataset).
      skip_bad: skip (and count) files that raise `DataError` instead of stopping with that error.
      executor: where the jobs run (`gpd_jax.data.executors`; default: `workers` local processes).
    Raises `DataError` (naming the file) for a bad input file unless `skip_bad`, and `ValueError` when `out_dir`
    holds a build with other settings or of another set of files.
    """
    t0 = time.time()
    sample_cfg = sample_cfg or preprocess.SampleConfig()
    files = find_scenarios(db)
    h = hashlib.sha256()
    for f in files:
        h.update(f"{f.key}\0{os.path.getsize(f.path)}\n".encode())
    os.makedirs(out_dir, exist_ok=True)
    store.clean_temporaries(out_dir)
    settings = {"source": "scenarionet", "db": os.path.abspath(db), "seed": seed, "split": split,
                "max_per_log": max_per_log, "per_job": per_job, "skip_bad": skip_bad,
                "num_files": len(files), "files_sha256": h.hexdigest(),
                "sample_config": dataclasses.asdict(sample_cfg)}
    check_settings(out_dir, settings)
    index = _scenarionet_index(out_dir, files, h.hexdigest())
    jobs = _plan_scenarionet_jobs([f.path for f in files], index, seed, split, per_job)
    bound = _ScenarioNetBound(out_dir, sample_cfg, max_per_log, seed, skip_bad)
    results = run_jobs(jobs, bound, out_dir, workers, "scenarionet build", executor)
    failed = [r for r in results if r.get("error")]
    if failed:
        raise DataError(*failed[0]["error"])
    stats: Counter = Counter()
    for r in results:
        stats.update(r.get("stats", {}))
    short = stats.get("skip_log_too_short", 0)
    if short:
        log.warning("%d of %d scenarios are shorter than the %d frames (%.1f s at 10 Hz) a sample needs and gave "
                    "no sample (Waymo's scenarios are 91 frames)", short, len(files), sample_cfg.num_frames,
                    sample_cfg.num_frames / 10)
    man = finish(out_dir, settings, results, time.time() - t0)
    return man
