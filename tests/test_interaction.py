"""INTERACTION importer and Lanelet2 reader: a tiny dataset the tests write themselves (a track CSV and a Lanelet2
.osm of a straight two-way road) -> RawLog -> samples -> store.

Covers CSV parsing (types kept and dropped, sizes, gaps), the projection (against the built-in transverse Mercator),
lanelet bound alignment, direction and centrelines, windows and the ego choice, samples in the store's
conventions, the fixed split by site, the build through the command line, and bad files (missing column,
non-numeric value, unknown map, bad map, repeated rows, wrong frame period, headings against the velocities).
"""

import csv
import dataclasses
import os
from collections import Counter

import numpy as np
import pytest

from gpd_jax.data import preprocess, store
from gpd_jax.data.__main__ import main as data_main
from gpd_jax.data.errors import DataError
from gpd_jax.data.sources import gpkg, interaction, lanelet2
from gpd_jax.scene import TYPE_ID

SITE = "DR_TST_Road_XX"
F = 160  # frames in the fixture file (16 s): window starts 0 and 30
HEADER = ["track_id", "frame_id", "timestamp_ms", "agent_type", "x", "y", "vx", "vy", "psi_rad", "length", "width"]
X0, X1 = 900.0, 1200.0  # the road's extent (m, local frame)
LANE_W = 3.5


# ------------------------------------------------------------------------------------------------ fixtures
def _lonlat(x, y):
    """Local metres -> (lat, lon) for Lanelet2's UtmProjector at origin (0, 0) (zone 31), by the built-in inverse."""
    ox, oy = gpkg.lonlat_to_utm(np.array([0.0]), np.array([0.0]), 31)
    lon, lat = gpkg.utm_to_lonlat(np.asarray(x, float) + ox[0], np.asarray(y, float) + oy[0], 31)
    return lat, lon


def write_osm(path, lanelets=None, extra=""):
    """A two-way straight road along +x: lanelet 100 eastbound (y 0..3.5), lanelet 101 westbound (y -3.5..0), with
    bound ways stored in mixed directions (the reader must align them), plus a crosswalk and a keep-out area."""
    xs = np.linspace(X0, X1, 4)
    lines = {  # way id -> points (local metres), in the order written to the file
        10: [(x, LANE_W) for x in xs],          # eastbound left bound, written west -> east
        11: [(x, 0.0) for x in xs[::-1]],       # centre line, written east -> west
        12: [(x, -LANE_W) for x in xs],         # westbound left bound (its left is the south), west -> east
        13: [(1000.0, -LANE_W), (1000.0, LANE_W)],  # crosswalk sides
        14: [(1004.0, -LANE_W), (1004.0, LANE_W)],
    }
    nodes, ways, nid = [], [], 1000
    for wid, pts in lines.items():
        lat, lon = _lonlat([p[0] for p in pts], [p[1] for p in pts])
        refs = []
        for a, b in zip(lat, lon):
            nodes.append(f'  <node id="{nid}" visible="true" version="1" lat="{a:.11f}" lon="{b:.11f}" />')
            refs.append(nid)
            nid += 1
        ways.append(f'  <way id="{wid}" visible="true" version="1">' + "".join(f'<nd ref="{r}" />' for r in refs)
                    + '<tag k="type" v="line_thin" /></way>')

    def rel(rid, left, right, subtype="road"):
        return (f'  <relation id="{rid}" visible="true" version="1"><member type="way" ref="{left}" role="left" />'
                f'<member type="way" ref="{right}" role="right" /><tag k="type" v="lanelet" />'
                f'<tag k="subtype" v="{subtype}" /><tag k="one_way" v="yes" /></relation>')

    rels = lanelets if lanelets is not None else [rel(100, 10, 11), rel(101, 12, 11), rel(102, 13, 14, "crosswalk")]
    rels = list(rels) + ['  <relation id="200" visible="true" version="1"><tag k="type" v="multipolygon" />'
                         '<tag k="subtype" v="keepout" /></relation>']
    with open(path, "w") as f:
        f.write('<?xml version="1.0"?>\n<osm version="0.6" generator="lanelet2">\n' + "\n".join(nodes + ways + rels)
                + extra + "\n</osm>\n")


def track_rows():
    """Track 1: a car eastbound at 5 m/s for all 160 frames; 2: a car parked on the eastbound lane; 3: a truck
    westbound at 8 m/s, frames 11-120 only; 4: a car eastbound 4 m/s with frames 50-59 missing; 7: a pedestrian."""
    rows = []
    for f in range(1, F + 1):
        t = (f - 1) * 0.1
        rows.append([1, f, f * 100, "car", 950 + 5 * t, 1.75, 5.0, 0.0, 0.0, 4.5, 1.8])
        rows.append([2, f, f * 100, "car", 1010.0, 1.75, 0.0, 0.0, 0.0, 4.0, 1.7])
        if 11 <= f <= 120:
            rows.append([3, f, f * 100, "truck", 1050 - 8 * t, -1.75, -8.0, 0.0, np.pi, 9.0, 2.5])
        if not 50 <= f <= 59:
            rows.append([4, f, f * 100, "car", 930 + 4 * t, 1.75, 4.0, 0.0, 0.0, 4.6, 1.9])
        if f <= 40:
            rows.append([7, f, f * 100, "pedestrian/bicycle", 1002.0, -3.0 + 0.1 * t, 0.0, 1.0, np.pi / 2, 0.5, 0.5])
    return rows


def write_csv(path, rows=None, header=HEADER):
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(track_rows() if rows is None else rows)


@pytest.fixture
def db(tmp_path):
    """A dataset root with one site: two track files and the map."""
    root = tmp_path / "interaction"
    os.makedirs(root / "recorded_trackfiles" / SITE)
    os.makedirs(root / "maps")
    write_csv(root / "recorded_trackfiles" / SITE / "vehicle_tracks_000.csv")
    write_csv(root / "recorded_trackfiles" / SITE / "vehicle_tracks_001.csv")
    write_osm(root / "maps" / f"{SITE}.osm")
    return str(root)


def _track(db, name="vehicle_tracks_000.csv"):
    return os.path.join(db, "recorded_trackfiles", SITE, name)


# ------------------------------------------------------------------------------------------------- tracks
def test_tracks_parsed_types_sizes_gaps(db):
    stats = Counter()
    raw = interaction.read_tracks(_track(db), stats=stats)
    assert raw.location == SITE and raw.name == f"{SITE}/vehicle_tracks_000" and raw.ego_index is None
    assert raw.agent_ids == ("1", "2", "3", "4") and raw.num_frames == F
    assert stats["tracks_dropped_pedestrian/bicycle"] == 1
    t = dict(zip(raw.agent_ids, raw.agent_type))
    assert t["1"] == TYPE_ID["car"] and t["3"] == TYPE_ID["truck"]
    np.testing.assert_allclose(raw.agent_size[2], [9.0, 2.5])
    np.testing.assert_allclose(raw.timestamps[:3], [0.0, 0.1, 0.2])
    v = raw.agent_valid
    assert v[:, 0].all() and v[10:120, 2].all() and not v[:10, 2].any() and not v[120:, 2].any()
    assert not v[49:59, 3].any() and v[:49, 3].all() and v[59:, 3].all()
    np.testing.assert_allclose(raw.agent_xy[20, 0], [960.0, 1.75])
    assert np.isnan(raw.agent_xy[0, 2]).all() and raw.agent_heading[20, 2] == pytest.approx(np.pi)


def test_columns_in_any_order(db, tmp_path):
    order = HEADER[::-1]
    rows = [r[::-1] for r in track_rows()]
    p = tmp_path / "shuffled.csv"
    write_csv(p, rows, order)
    a, b = interaction.read_tracks(p, SITE), interaction.read_tracks(_track(db))
    np.testing.assert_array_equal(a.agent_xy, b.agent_xy)
    np.testing.assert_array_equal(a.agent_type, b.agent_type)


# ------------------------------------------------------------------------------------------------ lanelet2
def test_projection_matches_builtin_transverse_mercator():
    proj = lanelet2.local_projector(0.0, 0.0)
    x, y = proj(np.array([0.0, 0.0, 0.009, 0.0091]), np.array([0.0, 0.01, 0.009, 0.0093]))
    assert abs(x[0]) < 1e-6 and abs(y[0]) < 1e-6
    ox, oy = gpkg.lonlat_to_utm(np.array([0.0]), np.array([0.0]), 31)
    bx, by = gpkg.lonlat_to_utm(np.array([0.0, 0.01, 0.009, 0.0093]), np.array([0.0, 0.0, 0.009, 0.0091]), 31)
    np.testing.assert_allclose(x, bx - ox[0], atol=1e-3)
    np.testing.assert_allclose(y, by - oy[0], atol=1e-3)
    # 0.01 degrees of longitude on the equator, at UTM zone 31's scale 3 degrees off its central meridian
    assert x[1] == pytest.approx(1113.19 * 1.00097, rel=2e-4) and abs(y[1]) < 1e-6
    assert lanelet2.utm_zone(0.0, 0.0) == (31, False) and lanelet2.utm_zone(-33.0, 151.2) == (56, True)


def test_lanelets_aligned_directed_and_averaged(db):
    m = lanelet2.read_lanelet2(os.path.join(db, "maps", f"{SITE}.osm"))
    assert [ll.id for ll in m.lanelets] == ["100", "101", "102"]
    assert [ll.id for ll in m.vehicle_lanelets] == ["100", "101"]
    assert m.counts["relation_multipolygon_keepout"] == 1 and m.counts["bounds_reversed"] == 2
    east, west = m.lanelets[0], m.lanelets[1]
    # eastbound: travels +x, left bound at y = 3.5, centreline at y = 1.75
    assert east.centreline[-1, 0] - east.centreline[0, 0] == pytest.approx(X1 - X0, abs=0.01)
    np.testing.assert_allclose(east.centreline[:, 1], LANE_W / 2, atol=0.01)
    np.testing.assert_allclose(east.left[:, 1], LANE_W, atol=0.01)
    # westbound: travels -x, its left bound (stored west -> east) is the south kerb, its right the centre line
    assert west.centreline[-1, 0] - west.centreline[0, 0] == pytest.approx(X0 - X1, abs=0.01)
    np.testing.assert_allclose(west.centreline[:, 1], -LANE_W / 2, atol=0.01)
    np.testing.assert_allclose(west.left[:, 1], -LANE_W, atol=0.01)
    assert west.left[0, 0] > west.left[-1, 0] and west.right[0, 0] > west.right[-1, 0]
    lanes = lanelet2.read_lanelet2_lanes(os.path.join(db, "maps", f"{SITE}.osm"))
    assert len(lanes) == 2 and all(lane.shape[1] == 2 for lane in lanes)
    ring = lanelet2.lanelet_ring(east.left, east.right)
    area = 0.5 * abs(np.dot(ring[:, 0], np.roll(ring[:, 1], -1)) - np.dot(ring[:, 1], np.roll(ring[:, 0], -1)))
    assert area == pytest.approx((X1 - X0) * LANE_W, rel=1e-3)


def test_a_bound_made_of_several_ways(tmp_path):
    """levelXData's maps (inD, rounD, highD) give a bound as several ways meeting end to end, in any direction:
    they read as the one way they make up."""
    p = tmp_path / "split.osm"
    split_ways = ('\n  <way id="20"><nd ref="1000" /><nd ref="1001" /></way>'  # way 10's first half
                  '\n  <way id="21"><nd ref="1003" /><nd ref="1002" /><nd ref="1001" /></way>')  # the rest, reversed
    rel = ('  <relation id="{}"><member type="way" ref="{}" role="left" />{}<member type="way" ref="11" '
           'role="right" /><tag k="type" v="lanelet" /></relation>')
    write_osm(p, lanelets=[rel.format(100, 10, ""), rel.format(110, 21, '<member type="way" ref="20" role="left" />')],
              extra=split_ways)
    whole, split = lanelet2.read_lanelet2(p).lanelets
    np.testing.assert_allclose(split.left, whole.left, atol=1e-6)
    np.testing.assert_allclose(split.centreline, whole.centreline, atol=1e-6)


def test_centreline_of_bounds_with_different_vertex_counts():
    left = np.array([[0.0, 2.0], [10.0, 2.0]])
    right = np.array([[0.0, 0.0], [5.0, 0.0], [7.5, 0.0], [10.0, 0.0]])
    c = lanelet2.centreline(left, right)
    np.testing.assert_allclose(c[:, 0], [0.0, 5.0, 7.5, 10.0])
    np.testing.assert_allclose(c[:, 1], 1.0)
    l2, r2, flips = lanelet2.align_bounds(left[::-1], right)
    assert flips == 1 and l2[0, 0] == 0.0 and r2[0, 0] == 0.0


# ------------------------------------------------------------------------------------------- windows, ego
def test_windows_and_ego_choice(db):
    raw = interaction.read_log(interaction.find_track_files(db)[0], db)
    stats = Counter()
    wins = interaction.choose_windows(raw, seed=0, stats=stats)
    # starts 0 and 30; valid throughout and moving >= 10 m: only track 1 (2 parks, 3 comes late, 4 has a gap)
    assert wins == [(0, 0), (30, 0)]
    assert interaction.choose_windows(raw, seed=0, min_travel=1000.0, stats=stats) == []
    assert stats["skip_no_ego_candidate"] == 2
    # the draw is seeded: a second mover valid throughout -> both get chosen across seeds, the same for one seed
    xy = raw.agent_xy.copy()
    xy[:, 1, 0] = 1010.0 + 2.0 * raw.timestamps  # track 2 now moves 20 m per window
    raw2 = dataclasses.replace(raw, agent_xy=xy)
    egos = {interaction.choose_windows(raw2, seed=s)[0][1] for s in range(12)}
    assert egos == {0, 1}
    assert interaction.choose_windows(raw2, seed=3) == interaction.choose_windows(raw2, seed=3)


def test_samples_in_store_conventions(db):
    raw = interaction.read_log(interaction.find_track_files(db)[0], db)
    cfg = preprocess.SampleConfig()
    pairs = interaction.log_samples(raw, cfg, seed=0)
    assert [sid for sid, _ in pairs] == [f"{SITE}/vehicle_tracks_000/0/1", f"{SITE}/vehicle_tracks_000/30/1"]
    s = pairs[0][1]
    assert set(s) == set(preprocess.SAMPLE_SPEC)
    np.testing.assert_allclose(s["xy"][20, 0], 0.0, atol=1e-4)
    assert s["heading"][20, 0] == pytest.approx(0.0) and s["valid"][:, 0].all()
    np.testing.assert_allclose(s["xy"][100, 0], [40.0, 0.0], atol=1e-3)  # 5 m/s forward for 8 s
    assert s["agent_type"][0] == TYPE_ID["ego"]
    # nearest first: track 4 22 m behind, the parked car 50 m ahead (1010 - 960), the oncoming truck 74 m ahead on
    # the other lane
    np.testing.assert_allclose(s["xy"][20, 1], [-22.0, 0.0], atol=1e-3)
    np.testing.assert_allclose(s["xy"][20, 2], [50.0, 0.0], atol=1e-3)
    np.testing.assert_allclose(s["size"][2], [4.0, 1.7])
    assert s["valid"][:, 2].all() and not s["valid"][49:59, 1].any() and s["valid"][59:, 1].all()
    assert s["agent_type"].tolist()[:4] == [TYPE_ID["ego"], TYPE_ID["car"], TYPE_ID["car"], TYPE_ID["truck"]]
    k = s["agent_type"].tolist().index(TYPE_ID["truck"])
    assert abs(abs(s["heading"][20, k]) - np.pi) < 1e-3 and s["xy"][20, k, 1] == pytest.approx(-3.5, abs=1e-3)
    # lanes: the ego's lane runs along +x at y = 0, the other along -x at y = -3.5
    pv = s["polyline_valid"]
    assert pv.any(1).sum() >= 2
    dirs = []
    for i in np.nonzero(pv.any(1))[0]:
        p = s["polylines"][i][pv[i]]
        dirs.append((round(float(np.median(p[:, 1])), 1), np.sign(p[-1, 0] - p[0, 0])))
    assert (0.0, 1.0) in dirs and (-3.5, -1.0) in dirs
    # drivable area: one lane ring covering both lanes, and two road edges at y = +1.75 and y = -5.25
    assert s["road_polygon_valid"].any(1).sum() >= 1
    ev = s["road_edge_valid"]
    ys = sorted(float(np.median(s["road_edges"][i][ev[i]][:, 1])) for i in np.nonzero(ev.any(1))[0])
    assert len(ys) == 2 and ys == pytest.approx([-LANE_W - 1.75, LANE_W - 1.75], abs=0.05)


# ----------------------------------------------------------------------------------------------- split, build
def test_site_split_is_by_place():
    sp = interaction.SITE_SPLITS
    by = {k: sorted(s for s, v in sp.items() if v == k) for k in ("train", "val", "test")}
    assert len(by["test"]) >= 2 and len(by["val"]) >= 1 and by["train"] and set(sp.values()) == set(by)
    assert len({sp[s] for s in sp if "_EP" in s}) == 1  # the EP sites (one city code) stay together
    assert interaction.site_splits(["DR_USA_Roundabout_SR"], None) == {"DR_USA_Roundabout_SR": "val"}
    with pytest.raises(DataError, match="give --split"):
        interaction.site_splits([SITE], None)


def test_cli_build_store(db, tmp_path, capsys):
    out = str(tmp_path / "store")
    argv = ["build", "--source", "interaction", "--db", db, "--out", out, "--split", "val", "--sites", SITE,
            "--workers", "1"]
    assert data_main(argv) == 0
    man = store.read_manifest(out)
    assert man["splits"]["val"]["num_samples"] == 4 and man["build"]["source"] == "interaction"
    assert man["build"]["sites"][SITE] == {"split": "val", "files": 2, "samples": 4, "hours": round(2 * F / 36000, 3)}
    shard = store.Shard(store.list_shards(out, "val")[0])
    assert shard.meta["locations"] == [SITE, SITE]
    assert data_main(argv) == 0  # resumes: nothing to do
    argv[argv.index("val")] = "train"
    assert data_main(argv) == 2  # other settings in the same folder
    assert "other settings" in capsys.readouterr().err
    assert data_main(["build", "--source", "interaction", "--out", out]) == 2  # no --db
    assert data_main(["build", "--source", "sumo", "--sites", SITE, "--out", out]) == 2


# ------------------------------------------------------------------------------------------------ bad files
def _bad_csv(tmp_path, rows=None, header=HEADER):
    p = tmp_path / "bad.csv"
    write_csv(p, rows, header)
    return p


def test_missing_column(tmp_path):
    p = _bad_csv(tmp_path, [r[:8] + r[9:] for r in track_rows()], HEADER[:8] + HEADER[9:])
    with pytest.raises(DataError, match=r"bad\.csv: missing column\(s\) psi_rad"):
        interaction.read_tracks(p, SITE)


def test_non_numeric_value_names_line_and_column(tmp_path):
    rows = track_rows()
    rows[5][4] = "12,5m"
    with pytest.raises(DataError, match=r"bad\.csv: line 7: column 'x' = '12,5m' is not a number"):
        interaction.read_tracks(_bad_csv(tmp_path, rows), SITE)
    rows = track_rows()
    rows[2][1] = "2.5"
    with pytest.raises(DataError, match=r"line 4: frame_id = '2.5' is not an integer"):
        interaction.read_tracks(_bad_csv(tmp_path, rows), SITE)


def test_short_row_repeated_row_frame_period_heading(tmp_path):
    rows = track_rows()
    rows[2] = rows[2][:5]
    with pytest.raises(DataError, match="line 4 has 5 fields"):
        interaction.read_tracks(_bad_csv(tmp_path, rows), SITE)
    rows = track_rows()
    rows.append(list(rows[0]))
    with pytest.raises(DataError, match="track 1 is listed more than once at frame_id 1"):
        interaction.read_tracks(_bad_csv(tmp_path, rows), SITE)
    rows = [[*r[:2], r[1] * 40, *r[3:]] for r in track_rows()]  # 25 Hz timestamps
    with pytest.raises(DataError, match="not a 10 Hz recording"):
        interaction.read_tracks(_bad_csv(tmp_path, rows), SITE)
    rows = [[*r[:8], r[8] + np.pi, *r[9:]] for r in track_rows()]  # headings turned half a turn
    with pytest.raises(DataError, match="psi_rad disagrees with the direction of"):
        interaction.read_tracks(_bad_csv(tmp_path, rows), SITE)
    open(tmp_path / "empty.csv", "w").close()
    with pytest.raises(DataError, match="empty file"):
        interaction.read_tracks(tmp_path / "empty.csv", SITE)
    with pytest.raises(DataError, match="no vehicle rows"):
        interaction.read_tracks(_bad_csv(tmp_path, [r for r in track_rows() if r[3] != "car" and r[3] != "truck"]),
                                SITE)


def test_unknown_map_and_not_a_dataset(db, tmp_path):
    os.remove(os.path.join(db, "maps", f"{SITE}.osm"))
    with pytest.raises(DataError, match=r"vehicle_tracks_000\.csv: unknown map: site 'DR_TST_Road_XX' has no "
                                        r"Lanelet2 map .*DR_TST_Road_XX\.osm"):
        interaction.find_track_files(db)
    with pytest.raises(DataError, match="not an INTERACTION dataset folder"):
        interaction.find_track_files(str(tmp_path))
    with pytest.raises(DataError, match="site 'NOPE' has no vehicle_tracks"):
        interaction.find_track_files(db, ["NOPE"])


def test_bad_maps(tmp_path):
    p = tmp_path / "m.osm"
    p.write_text("<osm><node id='1' lat='x' lon='0'/></osm>")
    with pytest.raises(DataError, match=r"m\.osm: node 1: lat='x'"):
        lanelet2.read_lanelet2(p)
    p.write_text("<osm><node id='1'")
    with pytest.raises(DataError, match=r"m\.osm: not a Lanelet2 \.osm \(XML\) file"):
        lanelet2.read_lanelet2(p)
    p.write_text('<?xml version="1.0"?><!DOCTYPE lolz [<!ENTITY a "aaaaaaaaaa"><!ENTITY b "&a;&a;&a;&a;&a;&a;'
                 '&a;&a;&a;&a;"><!ENTITY c "&b;&b;&b;&b;&b;&b;&b;&b;&b;&b;">]><osm><node id="&c;" lat="0" '
                 'lon="0"/></osm>')
    with pytest.raises(DataError, match="holds no lanelet"):  # a small internal entity expands; nothing runs
        lanelet2.read_lanelet2(p)
    write_osm(p, lanelets=['  <relation id="5"><member type="way" ref="10" role="left" />'
                           '<tag k="type" v="lanelet" /></relation>'])
    with pytest.raises(DataError, match="lanelet 5 has no right bound"):
        lanelet2.read_lanelet2(p)
    write_osm(p, lanelets=['  <relation id="5"><member type="way" ref="10" role="left" /><member type="way" '
                           'ref="99" role="right" /><tag k="type" v="lanelet" /></relation>'])
    with pytest.raises(DataError, match="lanelet 5: its right bound names way 99, which is not in the file"):
        lanelet2.read_lanelet2(p)
    disjoint = ('  <relation id="5"><member type="way" ref="10" role="left" /><member type="way" ref="13" '
                'role="left" /><member type="way" ref="11" role="right" /><tag k="type" v="lanelet" /></relation>')
    write_osm(p, lanelets=[disjoint])
    with pytest.raises(DataError, match="lanelet 5: the ways 10, 13 of its left bound do not meet end to end"):
        lanelet2.read_lanelet2(p)
    write_osm(p, lanelets=[])
    with pytest.raises(DataError, match="holds no lanelet"):
        lanelet2.read_lanelet2(p)
    with pytest.raises(DataError, match="no such map file"):
        lanelet2.read_lanelet2(tmp_path / "none.osm")
