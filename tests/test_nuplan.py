"""nuPlan reader: log .db + map .gpkg fixtures written at test time in nuPlan's schema."""

from __future__ import annotations

import math
import sqlite3
import struct

import numpy as np
import pytest

from gpd_jax.data.errors import DataError
from gpd_jax.data.raw import RawLog
from gpd_jax.data.sources import gpkg, nuplan
from gpd_jax.scene import TYPE_ID

import nuplan_fixtures as fx

HAVE_PYPROJ = gpkg.have_pyproj()
BACKENDS = ["builtin", pytest.param("pyproj", marks=pytest.mark.skipif(not HAVE_PYPROJ, reason="no pyproj"))]


@pytest.fixture
def maps_root(tmp_path):
    root = tmp_path / "maps"
    fx.write_maps_root(root)
    return root


@pytest.fixture
def db(tmp_path):
    (tmp_path / "logs").mkdir()
    return fx.write_log_db(tmp_path / "logs" / "2021.05.12.22.00.38_veh-35_01008_01518.db")


@pytest.fixture
def raw(db, maps_root) -> RawLog:
    return nuplan.read_log(db, maps_root)


def _ids(raw: RawLog) -> dict[str, int]:
    return {fx.TRACKS[n].name: raw.agent_ids.index(fx.track_token(n).hex())
            for n in range(len(fx.TRACKS)) if fx.track_token(n).hex() in raw.agent_ids}


# ---------------------------------------------------------------------------------------------------------
# Log contents
# ---------------------------------------------------------------------------------------------------------


def test_shapes_name_location(raw, db):
    assert isinstance(raw, RawLog)
    assert raw.name == db.stem
    assert raw.location == fx.MAP_NAME
    assert raw.num_frames == fx.NUM_PC // 2
    assert raw.num_agents == 4  # ego + car + truck + bus
    f, n = raw.num_frames, raw.num_agents
    assert raw.agent_xy.shape == (f, n, 2) and raw.agent_xy.dtype == np.float64
    assert raw.agent_heading.shape == (f, n) and raw.agent_valid.shape == (f, n)
    assert raw.agent_size.shape == (n, 2) and raw.agent_size.dtype == np.float32
    assert raw.agent_type.shape == (n,) and raw.agent_type.dtype == np.int32
    assert len(set(raw.agent_ids)) == n


def test_subsampled_20hz_to_10hz(raw):
    # Every second lidar_pc in timestamp order (rows are stored scrambled): 20 Hz frames 0, 2, 4, ...
    expected_us = np.array([i * fx.PC_STEP_US + (i % 3) for i in range(0, fx.NUM_PC, 2)])
    np.testing.assert_allclose(raw.timestamps, expected_us * 1e-6, atol=1e-9)
    np.testing.assert_allclose(np.diff(raw.timestamps), 0.1, atol=3e-6)
    assert raw.timestamps[0] == 0.0


def test_ego_pose_rear_axle_to_centre(raw):
    assert raw.ego_index == 0 and raw.agent_ids[0] == "ego"
    assert raw.agent_type[0] == TYPE_ID["ego"]
    np.testing.assert_allclose(raw.agent_size[0], [5.176, 2.297], atol=1e-6)
    assert raw.agent_valid[:, 0].all()
    for k in range(raw.num_frames):
        rear, h = fx.ego_rear_axle(2 * k)
        np.testing.assert_allclose(raw.agent_heading[k, 0], h, atol=1e-9)
        centre = rear + 1.461 * np.array([math.cos(h), math.sin(h)])
        np.testing.assert_allclose(raw.agent_xy[k, 0], centre, atol=1e-6)
    # Consistency with the devkit's convention: centre is ahead of the rear axle along the heading.
    rear0, _ = fx.ego_rear_axle(0)
    assert np.dot(raw.agent_xy[0, 0] - rear0, fx.DIRECTION) == pytest.approx(nuplan.EGO_REAR_AXLE_TO_CENTER)


def test_quaternion_yaw_and_helpers():
    for yaw in (-3.0, -1.0, 0.0, 0.5, 3.1):
        assert nuplan.quaternion_yaw(math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)) == pytest.approx(yaw)
    xy = nuplan.rear_axle_to_center(np.zeros((1, 2)), np.array([math.pi / 2]))
    np.testing.assert_allclose(xy, [[0.0, 1.461]], atol=1e-12)


def test_tracks_across_frames_and_validity(raw):
    ids = _ids(raw)
    assert set(ids) == {"car", "truck", "bus"}  # ghost only in dropped frames; pedestrian dropped
    assert ids == {"car": 1, "bus": 2, "truck": 3}  # by first appearance (truck from frame 5), then row order
    for name, n in ids.items():
        tr = next(t for t in fx.TRACKS if t.name == name)
        kept = np.array([2 * k in tr.frames for k in range(raw.num_frames)])
        np.testing.assert_array_equal(raw.agent_valid[:, n], kept)
        assert np.isnan(raw.agent_xy[~kept, n]).all() and np.isnan(raw.agent_heading[~kept, n]).all()
        for k in np.flatnonzero(kept):
            xy, h = tr.pose(2 * k)
            np.testing.assert_allclose(raw.agent_xy[k, n], xy, atol=1e-6)  # the confident box wins in frame 0
            np.testing.assert_allclose(raw.agent_heading[k, n], fx.ROAD_HEADING, atol=1e-9)  # wrapped
    # Truck: 20 Hz frames 10..40 -> 10 Hz frames 5..20.
    np.testing.assert_array_equal(np.flatnonzero(raw.agent_valid[:, ids["truck"]]), np.arange(5, 21))


def test_sizes_and_types(raw):
    ids = _ids(raw)
    np.testing.assert_allclose(raw.agent_size[ids["car"]], [4.6, 1.9], atol=1e-6)
    np.testing.assert_allclose(raw.agent_size[ids["truck"]], [8.0, 2.5], atol=1e-6)
    np.testing.assert_allclose(raw.agent_size[ids["bus"]], [12.0, 2.6], atol=1e-6)  # from boxes (NULL track)
    assert raw.agent_type[ids["car"]] == TYPE_ID["car"]
    assert raw.agent_type[ids["truck"]] == TYPE_ID["truck"]
    assert raw.agent_type[ids["bus"]] == TYPE_ID["bus"]
    np.testing.assert_array_equal(
        nuplan.vehicle_type(np.array([4.0, 6.49, 6.5, 9.99, 10.0, 18.0])),
        [TYPE_ID[t] for t in ("car", "car", "truck", "truck", "bus", "bus")],
    )


# ---------------------------------------------------------------------------------------------------------
# Map: GeoPackage parsing and projection
# ---------------------------------------------------------------------------------------------------------


def _assert_lanes(lanes, names=("lane0", "chain"), atol=1e-3):
    u = fx.lane_polylines_utm()
    utm = {**u, **fx.merged_polylines_utm(), "connector_lane2": np.concatenate([u["connector"], u["lane2"][1:]])}
    assert len(lanes) == len(names)
    for lane, name in zip(sorted(lanes, key=lambda a: (a[0, 0], a[0, 1])),
                          sorted(names, key=lambda k: (utm[k][0, 0], utm[k][0, 1]))):
        np.testing.assert_allclose(lane, utm[name], atol=atol, rtol=0)


def test_lanes_read_and_cropped(raw):
    _assert_lanes(raw.lanes, atol=1e-9)  # same projection: untouched; the far lane is cropped away
    # The ego drives along lane 0.
    lane0 = min(raw.lanes, key=lambda a: np.linalg.norm(a[0] - fx.ORIGIN))
    rear, _ = fx.ego_rear_axle(0)
    assert np.min(np.linalg.norm(lane0 - rear, axis=1)) < 1e-6


def test_whole_map_without_margin(db, maps_root):
    raw = nuplan.read_log(db, maps_root, map_margin=None)
    _assert_lanes(raw.lanes, names=("lane0", "chain", "far"), atol=1e-9)


def test_unmerged_lanes(db, maps_root):
    raw = nuplan.read_log(db, maps_root, map_margin=None, merge_lanes=False)
    _assert_lanes(raw.lanes, names=("lane0", "lane1", "connector", "lane2", "far"), atol=1e-9)
    m = nuplan.read_map_lanes(fx.write_maps_root(maps_root), "EPSG:32611", merge=False)
    assert m.is_connector.tolist() == [False, False, True, False, False]  # fid order 1, 2, 3, 4, 6


def test_merge_chains_rule():
    # a -> b -> c, then c forks to d and e; f joins e; g <-> h is a loop; i stands alone.
    edges = [("a", "b"), ("b", "c"), ("c", "d"), ("c", "e"), ("f", "e"), ("g", "h"), ("h", "g"), ("x", "i")]
    chains = nuplan.merge_chains(list("abcdefghi"), edges)
    assert chains == [["a", "b", "c"], ["d"], ["e"], ["f"], ["i"], ["g", "h"]]


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("srs", [4326, 32612])
def test_lanes_projected_from_other_crs(tmp_path, db, srs, backend):
    root = tmp_path / f"maps_{srs}"
    fx.write_maps_root(root, srs=srs)
    raw = nuplan.read_log(db, root, projection=backend)
    _assert_lanes(raw.lanes, atol=1e-3)


@pytest.mark.parametrize("little", [True, False])
@pytest.mark.parametrize("envelope", [0, 1, 2, 4])
def test_blob_variants(tmp_path, db, little, envelope):
    root = tmp_path / "maps"
    fx.write_maps_root(root, little=little, envelope=envelope, with_z=envelope == 2)
    _assert_lanes(nuplan.read_log(db, root).lanes, atol=1e-9)


def test_multilinestring_parts_become_lanes(tmp_path, db):
    root = tmp_path / "maps"
    map_path = fx.write_maps_root(root, multi=True, srs=4326, little=False)
    m = nuplan.read_map_lanes(map_path, "EPSG:32611", projection="builtin")
    # The two parts of lane 1's row stay separate (and unmerged); the connector still merges into lane 2.
    assert len(m.lanes) == 4 and not m.is_connector.any()
    _assert_lanes(m.lanes, names=("lane0", "lane1", "far", "connector_lane2"), atol=1e-3)


def test_target_frame_without_meta_table(tmp_path, db):
    # No meta table: the frame comes from ego_pose.epsg, or else from the city's known UTM zone.
    root = tmp_path / "maps"
    fx.write_maps_root(root, srs=4326, meta=False)
    _assert_lanes(nuplan.read_log(db, root).lanes)
    db2 = fx.write_log_db(tmp_path / "noepsg.db", epsg=None)
    _assert_lanes(nuplan.read_log(db2, root).lanes)


def test_builtin_projection_matches_proj_reference_values():
    # (lon, lat) -> UTM pairs computed once with PROJ 9 (pyproj 3.7), pinned here.
    ref = [
        (32611, -115.1728, 36.1147, 664450.9750620188, 3998216.3353241864),
        (32619, -71.0589, 42.3601, 330448.1064788103, 4691812.0594693655),
        (32648, 103.7876, 1.2995, 365114.5766012096, 143666.41082244882),
        (32617, -79.9476, 40.4106, 589292.9891344343, 4473863.06842307),
        (32612, -115.1728, 36.1147, 124358.69891881087, 4004741.117686563),  # 9 degrees off-meridian
    ]
    for code, lon, lat, x, y in ref:
        fwd = gpkg.make_transform(4326, f"EPSG:{code}", backend="builtin")
        inv = gpkg.make_transform(f"epsg:{code}", "EPSG:4326", backend="builtin")
        np.testing.assert_allclose(fwd(np.array([lon]), np.array([lat])), [[x], [y]], atol=1e-6, rtol=0)
        np.testing.assert_allclose(inv(np.array([x]), np.array([y])), [[lon], [lat]], atol=1e-11, rtol=0)


@pytest.mark.skipif(not HAVE_PYPROJ, reason="no pyproj")
def test_builtin_projection_matches_pyproj():
    rng = np.random.default_rng(0)
    lon, lat = -117 + rng.uniform(-5, 5, 200), 36 + rng.uniform(-3, 3, 200)
    for src, dst in [(4326, 32611), (32612, 32611), ("+proj=utm +zone=11 +datum=WGS84 +units=m", 4326)]:
        x, y = gpkg.make_transform(4326, src, backend="pyproj")(lon, lat)
        a = gpkg.make_transform(src, dst, backend="builtin")(x, y)
        b = gpkg.make_transform(src, dst, backend="pyproj")(x, y)
        np.testing.assert_allclose(a, b, atol=1e-6, rtol=0)


def test_parse_gpkg_blob_units():
    xy = np.array([[1.0, 2.0], [3.0, 4.5]])
    g = gpkg.parse_gpkg_blob(fx.gp_blob(fx.wkb_linestring(xy, little=False), 32611, little=False, envelope=1, xy=xy))
    assert g.kind == "LineString" and g.srs_id == 32611
    np.testing.assert_array_equal(g.parts[0], xy)
    empty = b"GP" + bytes([0, 0b1_0001]) + struct.pack("<i", 4326)
    assert gpkg.parse_gpkg_blob(empty).is_empty
    ewkb = struct.pack("<BIiI", 1, 0x8000_0002 | 0x2000_0000, 4326, 2) + np.array(
        [[1, 2, 9], [3, 4, 9]], "<f8").tobytes()  # EWKB LineString Z with SRID
    np.testing.assert_array_equal(gpkg.parse_wkb(ewkb).parts[0], [[1, 2], [3, 4]])
    for bad in (b"XX" + bytes(6), fx.gp_blob(fx.wkb_linestring(xy), 1)[:-1],
                fx.gp_blob(struct.pack("<BI", 1, 17), 1), b"GP" + bytes([0, 0b1110]) + bytes(4)):
        with pytest.raises(gpkg.GeometryError):
            gpkg.parse_gpkg_blob(bad)


# ---------------------------------------------------------------------------------------------------------
# Map layouts
# ---------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("layout", ["json", "versions", "flat"])
def test_map_layouts(tmp_path, layout):
    root = tmp_path / "maps"
    expected = fx.write_maps_root(root, layout=layout)
    assert nuplan.find_map(root, fx.MAP_NAME) == (fx.MAP_NAME, expected)
    assert nuplan.find_map(root, fx.MAP_NAME + ".gpkg") == (fx.MAP_NAME, expected)
    assert nuplan.find_map(root, "unknown-map", "las_vegas") == (fx.MAP_NAME, expected)
    assert nuplan.find_map(tmp_path, fx.MAP_NAME)[1] == expected  # the folder above "maps"


# ---------------------------------------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------------------------------------


def _raises(match, fn, *args, name, **kwargs):
    with pytest.raises(DataError, match=match) as info:
        fn(*args, **kwargs)
    assert name in str(info.value) and name in info.value.path, str(info.value)
    return info.value


def test_db_not_a_database(tmp_path, maps_root):
    bad = tmp_path / "garbage.db"
    bad.write_bytes(b"this is not sqlite" * 100)
    _raises("not a readable", nuplan.read_log, bad, maps_root, name="garbage.db")


def test_db_truncated(tmp_path, maps_root, db):
    data = db.read_bytes()
    cut = tmp_path / "cut.db"
    cut.write_bytes(data[: len(data) // 3])
    _raises("malformed|missing table", nuplan.read_log, cut, maps_root, name="cut.db")
    empty = tmp_path / "empty.db"
    empty.write_bytes(b"")
    _raises("missing table", nuplan.read_log, empty, maps_root, name="empty.db")


def test_db_missing_table(tmp_path, maps_root):
    db = fx.write_log_db(tmp_path / "nobox.db", drop_tables=("lidar_box",))
    _raises("missing table.*lidar_box", nuplan.read_log, db, maps_root, name="nobox.db")


def test_db_missing_file(tmp_path, maps_root):
    _raises("not found", nuplan.read_log, tmp_path / "nope.db", maps_root, name="nope.db")


def test_nan_ego_and_box(tmp_path, maps_root):
    db = fx.write_log_db(tmp_path / "nanego.db", nan_ego_frame=4)
    _raises("ego_pose of kept frame 2 .*NaN", nuplan.read_log, db, maps_root, name="nanego.db")
    db = fx.write_log_db(tmp_path / "nanbox.db", nan_box=True)
    _raises("NaN", nuplan.read_log, db, maps_root, name="nanbox.db")


def test_nan_ego_in_dropped_frame_is_harmless(tmp_path, maps_root):
    db = fx.write_log_db(tmp_path / "nanodd.db", nan_ego_frame=5)
    assert np.isfinite(nuplan.read_log(db, maps_root).agent_xy[:, 0]).all()


def test_frame_gap(tmp_path, maps_root):
    db = fx.write_log_db(tmp_path / "gap.db", skip_pc=(30,))
    _raises("not 10 Hz", nuplan.read_log, db, maps_root, name="gap.db")


def test_missing_map_for_map_version(tmp_path, maps_root):
    db = fx.write_log_db(tmp_path / "boston.db", map_version="us-ma-boston", location="boston")
    err = _raises("no map file.*us-ma-boston", nuplan.read_log, db, maps_root, name="boston.db")
    assert "9.12.1817" in err.reason  # the version the json names was looked for


def test_map_not_a_database(tmp_path, db):
    root = tmp_path / "maps"
    fx.write_maps_root(root).write_bytes(b"\x00garbage" * 64)
    _raises("not a readable GeoPackage", nuplan.read_log, db, root, name="map.gpkg")


def test_map_bad_blob(tmp_path, db):
    root = tmp_path / "maps"
    fx.write_maps_root(root, bad_blob=True)
    _raises("baseline_paths' fid 3: bad geometry blob", nuplan.read_log, db, root, name="map.gpkg")


def test_map_missing_layer(tmp_path, db):
    root = tmp_path / "maps"
    fx.write_maps_root(root, layers=("lanes_polygons", "lane_connectors"))
    _raises("layer 'baseline_paths' not found", nuplan.read_log, db, root, name="map.gpkg")


def test_map_nan_coordinate(tmp_path, db):
    root = tmp_path / "maps"
    fx.write_maps_root(root, nan_point=True)
    _raises("non-finite", nuplan.read_log, db, root, name="map.gpkg")


def test_map_missing_geometry_tables(tmp_path, db):
    root = tmp_path / "maps"
    path = fx.write_maps_root(root)
    conn = sqlite3.connect(path)
    conn.execute("DROP TABLE gpkg_geometry_columns")
    conn.commit()
    conn.close()
    _raises("not a GeoPackage", nuplan.read_log, db, root, name="map.gpkg")


def test_map_in_wrong_place_is_caught(tmp_path, db):
    # A map whose lanes are nowhere near the log (here: lon/lat degrees mislabelled as UTM metres).
    root = tmp_path / "maps"
    path = fx.write_maps_root(root, srs=4326)
    conn = sqlite3.connect(path)
    conn.execute("UPDATE gpkg_geometry_columns SET srs_id = -1")
    conn.commit()
    conn.close()
    _raises("no lane", nuplan.read_log, db, root, name=db.name)


# ---------------------------------------------------------------------------------------------------------
# iter_logs
# ---------------------------------------------------------------------------------------------------------


def test_iter_logs_directory_raise_and_skip(tmp_path, maps_root):
    logs = tmp_path / "split"
    (logs / "sub").mkdir(parents=True)
    fx.write_log_db(logs / "a.db")
    fx.write_log_db(logs / "sub" / "c.db", num_pc=40)
    fx.write_log_db(logs / "b.db", drop_tables=("track",))
    (logs / "d.db").write_bytes(b"junk" * 300)
    (logs / "notes.txt").write_text("ignored")

    with pytest.raises(DataError, match="b.db"):
        list(nuplan.iter_logs(logs, maps_root))

    errors: list = []
    raws = list(nuplan.iter_logs(logs, maps_root, skip_bad=True, errors=errors))
    assert [r.name for r in raws] == ["a", "c"]
    assert raws[1].num_frames == 20
    assert len(errors) == 2 and [e.path.rsplit("/", 1)[-1] for e in errors] == ["b.db", "d.db"]
    # A single file works too; an empty directory is an error.
    assert [r.name for r in nuplan.iter_logs(logs / "a.db", maps_root)] == ["a"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(DataError, match="no \\*.db"):
        list(nuplan.iter_logs(tmp_path / "empty", maps_root))


def test_iter_logs_reads_each_map_once(tmp_path, maps_root, monkeypatch):
    logs = tmp_path / "two"
    logs.mkdir()
    fx.write_log_db(logs / "a.db")
    fx.write_log_db(logs / "b.db")
    calls = []
    real = nuplan.read_map_lanes
    monkeypatch.setattr(nuplan, "read_map_lanes", lambda *a, **k: calls.append(a) or real(*a, **k))
    raws = list(nuplan.iter_logs(logs, maps_root))
    assert len(raws) == 2 and len(calls) == 1
    assert all(len(r.lanes) == 2 for r in raws)


# ---------------------------------------------------------------------------------------------------------
# Drivable area (map polygons -> sample geometry)
# ---------------------------------------------------------------------------------------------------------


def test_map_areas_read_by_layer(raw, maps_root):
    from gpd_jax.geometry import AREA_KIND_ID

    kinds = sorted(a.kind for a in raw.areas)
    # lanes_polygons lane0, lane1, lane2 (the far lane is cropped away), the intersection, the lay-by
    assert kinds == sorted([AREA_KIND_ID["lane"]] * 3 + [AREA_KIND_ID["junction"], AREA_KIND_ID["other"]])
    jn = [a for a in raw.areas if a.kind == AREA_KIND_ID["junction"]][0]
    np.testing.assert_allclose(jn.exterior, fx.intersection_ring_utm(), atol=1e-6)


def test_sample_geometry_from_the_map(raw):
    """Scene frame: the ego centre at the current frame sits on lane 0, x along the road, y lateral (left)."""
    import jax
    import jax.numpy as jnp

    from gpd_jax import geometry as geo
    from gpd_jax.data import preprocess

    cfg = preprocess.SampleConfig(num_history=5, num_future=10, view_half=150.0)
    s = preprocess.make_sample(raw, 0, 0, cfg)
    origin = np.array([*raw.agent_xy[cfg.current, 0], raw.agent_heading[cfg.current, 0]])
    road = geo.road_from_arrays(s, s["polylines"], s["polyline_valid"]).validate()

    def scene(along, lat):
        return preprocess.to_frame(fx.road_point(along, lat), origin)

    pts = {  # name: (road coordinates, on road, kinds, signed distance)
        "on lane 0": ((30.0, 0.0), True, [True, False, False], 1.75),
        "between the lanes": ((30.0, 1.75), True, [True, False, False], 3.5),
        "in the intersection": ((205.0, 15.0), True, [False, True, False], None),
        "in the lay-by": ((55.0, -6.0), True, [False, False, True], 2.0),
        "off the road": ((30.0, -5.0), False, [False, False, False], -3.25),
    }
    xy = jnp.asarray(np.stack([scene(*p[0]) for p in pts.values()]), jnp.float32)
    on = np.asarray(jax.jit(geo.on_road)(road, xy))
    kinds = np.asarray(jax.jit(geo.area_kinds)(road, xy))
    sd = np.asarray(jax.jit(geo.signed_distance_to_edge)(road, xy))
    for i, (name, (_, want_on, want_kinds, want_sd)) in enumerate(pts.items()):
        assert on[i] == want_on and kinds[i].tolist() == want_kinds, name
        if want_sd is not None:
            assert sd[i] == pytest.approx(want_sd, abs=0.02), (name, sd[i])
    heading, dist = jax.jit(geo.lane_direction)(road, xy[:1])
    assert float(dist[0]) == pytest.approx(0.0, abs=1e-3) and float(heading[0]) == pytest.approx(0.0, abs=1e-4)
    # the ego and the vehicles on the road are on it
    assert np.asarray(jax.jit(geo.on_road)(road, jnp.asarray(s["xy"][:, 0]))).all()
