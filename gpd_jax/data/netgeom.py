"""Near-duplicate road networks: a fingerprint of lane geometry that ignores rigid motion, and the check.

Splitting by network keeps a test scene off every training *network*, but not off training *geometry*: two
generated networks (or two copies of a real one under different names) can have the same roads. This module
finds such pairs, within a build (every val/test network against every train network) or across two stores.

Fingerprint (`NetFingerprint`): the network's lane centrelines (normal and internal junction lanes open to
passenger cars, as `sumo_networks.read_network_lanes` reads them) resampled every `spacing` = 2 m, centred on their
mean (which removes translation), plus a length-weighted histogram of lane directions (0.5 degree bins, smoothed),
the total lane length and the radius of gyration. Nothing in it depends on where the network lies; rotation
is resolved when two fingerprints are compared.

Comparison (`geometry_distance`), in metres:

1. screens: networks whose radii of gyration differ by more than 15 %, or whose distributions of point
   distances from the centre differ by more than `SCREEN_RADIAL` = 10 m (mean absolute difference of 200
   quantiles, a 1-D Wasserstein distance), cannot be near-duplicates (inf). Among 48 generated networks
   (16 per layout) these two screens left 2 of 360 same-layout pairs for the alignment;
2. candidate rotations: the peaks of the circular cross-correlation of the two direction histograms (a
   rotated copy has a rotated direction histogram; grids give 4 peaks, all tried);
3. for the best candidates, a few trimmed ICP steps (nearest neighbours, Kabsch) refine the rigid alignment;
4. the distance is the symmetric mean nearest-point distance between the aligned point sets (query points
   every 8 m against the other network's 2 m points).

Why this rather than the alternatives: sorted junction positions after principal-axis alignment break down
exactly on the networks that matter most here: a square grid has two equal principal axes, so its alignment
is arbitrary; pairwise-distance histograms (shape distributions) need no alignment but measured too little
margin (L1 0.04 between two different perturbed 4x4 grids against ~0.02 sampling noise). Aligning the lanes
themselves gives a figure in metres with a wide margin: measured on netgenerate networks, a translated and
rotated copy scores 0.0 m, two grids or spiders that netgenerate makes identical for different seeds (it
ignores --seed for them) 0.0 m, two grids whose nodes are perturbed with sigma = 10 m about 4 m, with sigma =
20 m 7-10 m, two random networks 40-90 m, a grid against a spider > 20 m. Near-duplicate = distance below
`DEFAULT_TOL` = 2.5 m (the 2 m / 8 m sampling leaves under 1 m for identical geometry). The same road layout
with a different number of lanes is also caught (its centrelines are within a lane width), on purpose: it
is the same road.

With the generator of `gpd_jax.data.sources.sumo_networks.NetSpec`, the closest same-layout pair among 48 generated
networks (16 per layout) measured 11 m apart, and seeds 7 and 11 share no near-duplicate (tests/test_data_netgeom.py).

Cost (2-core machine, shared): a fingerprint ~0.05-0.1 s for a generated network and ~1 s for SUMO's largest
real one (reading the XML dominates); a comparison that passes the screens ~0.1 s, one that fails them
microseconds. A 1000-scenario build (20 networks) checks its pairs in well under a second. Limits: a network that is a *crop* of
another is not found (the centring and the symmetric distance compare whole networks), nor a mirrored copy.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Iterable, Sequence

import numpy as np

from gpd_jax.data.errors import DataError

SPACING = 2.0  # metres between fingerprint points along a lane
QUERY_STRIDE = 4  # every 4th point (8 m) is a query point of the distance
DIR_BINS = 720  # 0.5 degree direction bins
MAX_POINTS = 400_000  # larger networks keep every k-th point
DEFAULT_TOL = 2.5  # metres: geometry_distance below this = near-duplicate
SCREEN_RG = 0.15  # relative difference of radii of gyration above which two networks are not compared
SCREEN_RADIAL = 10.0  # metres: W1 distance of centre-distance distributions above which they are not compared


@dataclasses.dataclass(frozen=True, eq=False)
class NetFingerprint:
    """Rigid-motion-free summary of a network's lane geometry (see the module docstring).

    name: what to call the network in reports (its location or file).
    points: f32[M, 2] lane points every `SPACING` m, centred on their mean.
    directions: f32[DIR_BINS] smoothed, length-weighted histogram of lane directions over [0, 2 pi).
    length: total lane length in metres.
    radius: radius of gyration of `points` in metres.
    """

    name: str
    points: np.ndarray
    directions: np.ndarray
    length: float
    radius: float

    def __post_init__(self):
        object.__setattr__(self, "_tree", None)
        object.__setattr__(self, "_radial", None)

    @property
    def radial(self) -> np.ndarray:
        """f64[200]: quantiles of the points' distances from the centre (rotation-free)."""
        if self._radial is None:
            r = np.linalg.norm(self.points.astype(np.float64), axis=-1)
            object.__setattr__(self, "_radial", np.quantile(r, np.linspace(0.005, 0.995, 200)))
        return self._radial

    @property
    def tree(self):
        if self._tree is None:
            from scipy.spatial import cKDTree

            object.__setattr__(self, "_tree", cKDTree(self.points))
        return self._tree


def _smooth_circular(h: np.ndarray, sigma_bins: float = 2.0) -> np.ndarray:
    r = int(3 * sigma_bins)
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma_bins) ** 2)
    hp = np.concatenate([h[-r:], h, h[:r]])
    return np.convolve(hp, k / k.sum(), "valid")


def fingerprint_lanes(lanes: Sequence[np.ndarray], name: str = "") -> NetFingerprint:
    """Fingerprint of lane polylines `f[P_i, 2]` (metres, any frame). Raises DataError if there are none."""
    from gpd_jax.data.preprocess import resample_polyline

    parts, ang, w = [], [], []
    for p in lanes:
        if len(p) < 2:
            continue
        r = resample_polyline(np.asarray(p, np.float64)[:, :2], SPACING)
        if len(r) < 2:
            continue
        d = np.diff(r, axis=0)
        parts.append(r)
        ang.append(np.arctan2(d[:, 1], d[:, 0]))
        w.append(np.linalg.norm(d, axis=-1))
    if not parts:
        raise DataError(name or None, "no lane geometry to fingerprint")
    xy = np.concatenate(parts)
    if len(xy) > MAX_POINTS:
        xy = xy[:: int(np.ceil(len(xy) / MAX_POINTS))]
    xy = xy - xy.mean(0)
    a, wt = np.concatenate(ang), np.concatenate(w)
    hist = np.bincount(((a % (2 * np.pi)) / (2 * np.pi) * DIR_BINS).astype(np.int64) % DIR_BINS, weights=wt,
                       minlength=DIR_BINS)
    return NetFingerprint(name=name, points=xy.astype(np.float32), directions=_smooth_circular(hist).astype(np.float32),
                          length=float(wt.sum()), radius=float(np.sqrt(np.mean(np.sum(xy ** 2, -1)))))


def fingerprint_network(net_path: str, name: str | None = None) -> NetFingerprint:
    """Fingerprint of a SUMO network file (`.net.xml[.gz]`); DataError if it is missing or unreadable."""
    from gpd_jax.data.sources.sumo_networks import read_network_lanes

    return fingerprint_lanes(read_network_lanes(net_path, merge_chains=False), name or net_path)


def save_fingerprint(fp: NetFingerprint, path: str) -> None:
    """Writes `fp` to `path` (.npz), atomically."""
    from gpd_jax.fsutil import atomic_path

    with atomic_path(path, suffix=".npz") as tmp:
        np.savez_compressed(tmp, points=fp.points, directions=fp.directions,
                            meta=np.array([fp.length, fp.radius]), name=np.array(fp.name))


def load_fingerprint(path: str) -> NetFingerprint:
    try:
        with np.load(path) as z:
            return NetFingerprint(name=str(z["name"]), points=z["points"], directions=z["directions"],
                                  length=float(z["meta"][0]), radius=float(z["meta"][1]))
    except (OSError, KeyError, ValueError) as e:
        raise DataError(path, f"unreadable network fingerprint: {e}") from e


def as_fingerprint(x) -> NetFingerprint:
    """A `NetFingerprint`, a saved fingerprint (`.npz`) or a SUMO network file -> `NetFingerprint`."""
    if isinstance(x, NetFingerprint):
        return x
    x = os.fspath(x)
    return load_fingerprint(x) if x.endswith(".npz") else fingerprint_network(x)


def _rot(t: float) -> np.ndarray:
    c, s = np.cos(t), np.sin(t)
    return np.array([[c, -s], [s, c]])


def _nn_mean(tree, q: np.ndarray) -> float:
    d, _ = tree.query(q)
    return float(np.mean(d))


def geometry_distance(a: NetFingerprint, b: NetFingerprint, candidates: int = 8, refine: int = 2,
                      icp_steps: int = 8) -> float:
    """Symmetric mean nearest-lane-point distance (metres) between `a` and `b` after the best rigid alignment
    of `b` onto `a`; inf when the screen says they cannot be near-duplicates. 0 for identical geometry."""
    if abs(a.radius - b.radius) > SCREEN_RG * max(a.radius, b.radius, 1e-9):
        return float("inf")
    if np.mean(np.abs(a.radial - b.radial)) > SCREEN_RADIAL:
        return float("inf")
    # rotations that line up the direction histograms: b rotated by +s bins matches a
    cc = np.real(np.fft.ifft(np.fft.fft(a.directions) * np.conj(np.fft.fft(b.directions))))
    peaks = np.nonzero((cc >= np.roll(cc, 1)) & (cc >= np.roll(cc, -1)))[0]
    peaks = peaks[np.argsort(-cc[peaks], kind="stable")][:candidates]
    qa, qb = a.points[::QUERY_STRIDE].astype(np.float64), b.points[::QUERY_STRIDE].astype(np.float64)
    scored = []
    for s in peaks:
        R = _rot(2 * np.pi * s / len(cc))
        scored.append((_nn_mean(a.tree, qb @ R.T), R))
    scored.sort(key=lambda t: t[0])
    best = float("inf")
    for _, R in scored[:refine]:
        y = qb @ R.T
        for _ in range(icp_steps):
            d, i = a.tree.query(y)
            keep = d <= 3 * np.median(d) + 1.0  # trimmed: parts with no counterpart do not pull
            if keep.sum() < 3:
                break
            P, Q = y[keep], a.points[i[keep]].astype(np.float64)
            pc, qc = P.mean(0), Q.mean(0)
            U, _, Vt = np.linalg.svd((P - pc).T @ (Q - qc))
            Rr = (U @ Vt).T
            if np.linalg.det(Rr) < 0:  # a reflection: not a rigid motion
                break
            y = (y - pc) @ Rr.T + qc
            R = Rr @ R
            if np.mean(d) < 1e-6:
                break
        # the whole of b under the same transform (y = R b + t, with t from the query points)
        t = (y - qb @ R.T).mean(0)
        bb = b.points.astype(np.float64) @ R.T + t
        from scipy.spatial import cKDTree

        fwd = _nn_mean(a.tree, y)
        back = _nn_mean(cKDTree(bb), qa)
        best = min(best, 0.5 * (fwd + back))
    return best


def near_duplicates(evaluated: Iterable, reference: Iterable, tol: float = DEFAULT_TOL) -> list[dict]:
    """Pairs (one of `evaluated`, one of `reference`) whose lane geometry nearly matches.

    Each list holds `NetFingerprint`s, saved fingerprints (`.npz`) or SUMO network files (`.net.xml[.gz]`), e.g.
    a store's test networks against another store's training networks (`store_fingerprints`). Returns
    `[{"evaluated": name, "reference": name, "distance_m": d}]` for every pair with `geometry_distance < tol`,
    sorted by distance.
    """
    ev = [as_fingerprint(x) for x in evaluated]
    ref = [as_fingerprint(x) for x in reference]
    out = []
    for e in ev:
        for r in ref:
            d = geometry_distance(e, r)
            if d < tol:
                out.append({"evaluated": e.name, "reference": r.name, "distance_m": round(d, 3)})
    return sorted(out, key=lambda x: x["distance_m"])


# ---------------------------------------------------------------------------------------------- in a store
NETWORKS_DIR = "_networks"
NETWORKS_INDEX = "index.json"


def networks_dir(data_dir: str) -> str:
    return os.path.join(data_dir, NETWORKS_DIR)


def read_network_index(data_dir: str) -> dict[str, dict]:
    """`DIR/_networks/index.json`: location -> {"layout", "split", "net", "fingerprint", ...} of a SUMO build.

    Raises DataError when the store has none (not a SUMO build, or built before networks were recorded)."""
    import json

    p = os.path.join(networks_dir(data_dir), NETWORKS_INDEX)
    try:
        with open(p) as f:
            return json.load(f)
    except FileNotFoundError as e:
        raise DataError(p, "no network index: not a SUMO store, or built before networks were recorded "
                           "(rebuild it to check it for near-duplicates)") from e
    except ValueError as e:
        raise DataError(p, f"corrupt network index: {e}") from e


def store_fingerprints(data_dir: str, splits: Sequence[str] | None = None) -> list[NetFingerprint]:
    """Fingerprints of the networks of a SUMO store (all, or those of `splits`), named by location."""
    index = read_network_index(data_dir)
    out = []
    for loc in sorted(index):
        rec = index[loc]
        if splits is not None and rec.get("split") not in splits:
            continue
        fp = load_fingerprint(os.path.join(networks_dir(data_dir), rec["fingerprint"]))
        out.append(dataclasses.replace(fp, name=loc))
    return out
