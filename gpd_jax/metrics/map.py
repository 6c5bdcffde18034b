"""Map metrics on decoded vector lanes: F1 of points within 1.5 m, lateral distance and Chamfer distance.

Paper-faithful definitions (the official GPD-1 `map_metrics.py`, `reference/sledge_nuplan.md` §2 and
`reference/gpd_official.md` §6), per frame:

* predictions are Hungarian-matched to the GT slots with the map tokenizer's cost (5 BCE + 2 L1, `matching.py`);
  a predicted line exists when its logit > 0 (probability 0.5);
* F1: index-aligned points of a matched pair, TP = points where both lines exist and 0 < d_k <= threshold
  (d = 0 is not a TP, a quirk); FP = P * #predicted lines - TP; FN = P * #GT lines - TP;
* lateral: for each TP point, the distance from p_k to the infinite line through GT points k and k+1 (the last
  point uses the line through P-2, P-1), summed and divided by the TP count;
* Chamfer ("map_chamfer", m^2): matched predictions and GT are multiplied by the GT line mask (padded slots become
  the origin and still take part in the minima, a quirk); for each point index k, pred line i is compared with the
  point k of every GT line j (squared distance); pred->gt takes the min over j, gt->pred the min over i; both are
  masked by the GT line mask, summed, and divided by 2 * P * #GT lines. The predicted existence is not used here:
  a matched prediction with logit <= 0 still counts on a valid GT slot.

Corrected Chamfer ("map_chamfer_corrected", metres): the symmetric mean nearest-point distance between the set of
points of existing predicted lines (logit > 0) and the set of points of valid GT lines,
0.5 * (mean_p min_g |p - g| + mean_g min_p |g - p|), per frame; frames where either set is empty are skipped and
counted in `map_chamfer_corrected_skipped`.

Diagnostic ("map_recall_by_length", with `length_edges`): the paper's per-point recall, TP / (P * #GT lines),
separately for GT lines grouped by arc length (e.g. short junction connectors against long through lanes),
pooled over all frames and steps. "map_recall_by_ends" (with `window_half`): the same recall for GT lines grouped
by how many of their two ends lie inside the frame's window rather than where the window clips them (0: a line
through the window, cut by its border only; 1; 2: a line that starts and ends at junctions or lane ends inside).

Cut-invariant score ("map_f1_cutfree", "map_precision_cutfree", "map_recall_cutfree", "map_chamfer_cutfree",
"map_chamfer_within_cutfree"; not in the paper, reported beside its F1, never instead): the paper's F1 compares
points by index inside Hungarian-matched lines, so the same road cut into lines differently (a chain merged or
not, a line split at another point) scores near zero. Here both line sets are the union of their segments,
sampled along their arc length (`cutfree_frame_sums`); precision is the share of predicted length within the
threshold (1.5 m) of any GT segment, recall the share of GT length within it of any predicted segment, F1 their
harmonic mean; the Chamfer is the symmetric length-weighted mean point-to-segment distance (metres), and
chamfer_within the same mean over the length within the threshold only. Lengths are pooled per step like TP.
"map_*_cutfree_directed" counts a hit only where the segment within the threshold runs the same way: the paper's
F1 also scores a line decoded the wrong way round as missed, and a binary raster cannot show the direction.

Aggregation: `map_metric_sums` sums over every leading batch dim except an optional step axis (the future frame,
kept when `step_axis` is given); `reduce_map_metrics` forms the ratios per step (TP/FP/FN and lateral / Chamfer
sums pooled over the data set, as the official code does per step) and averages the per-step values over steps.
Sums from several batches add up exactly (`accumulate`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from gpd_jax.metrics.matching import match_lines

LENGTH_EDGES_M = (5.0, 15.0, 30.0, 60.0)  # default GT line length groups of the recall diagnostic, metres
END_LABELS = ("no end inside (through the window)", "one end inside", "both ends inside")
BORDER_TOLERANCE_M = 0.5  # a GT line end this close to the window's border is where the window clipped it


def length_labels(edges=LENGTH_EDGES_M) -> list[str]:
    """Names of the length groups that `edges` (ascending, metres) make: '<5 m', '5-15 m', ..., '>=60 m'."""
    e = [f"{x:g}" for x in edges]
    return [f"<{e[0]} m"] + [f"{a}-{b} m" for a, b in zip(e[:-1], e[1:])] + [f">={e[-1]} m"]


_SUM_KEYS = ("tp", "fp", "fn", "lateral_sum", "chamfer_sum", "chamfer_den", "chamfer_corrected_sum",
             "chamfer_corrected_count", "chamfer_corrected_skipped")


def point_to_line_distance(p: jax.Array, a: jax.Array, b: jax.Array) -> jax.Array:
    """Distance from points p to the infinite lines through a and b (all f32[..., 2]) -> f32[...].

    Where a == b (a degenerate line) it is the distance |p - a|.
    """
    ab = b - a
    ap = p - a
    n = jnp.linalg.norm(ab, axis=-1)
    cross = jnp.abs(ab[..., 0] * ap[..., 1] - ab[..., 1] * ap[..., 0])
    safe = n > 1e-9
    return jnp.where(safe, cross / jnp.where(safe, n, 1.0), jnp.linalg.norm(ap, axis=-1))


def lateral_distances(pred: jax.Array, gt: jax.Array) -> jax.Array:
    """Index-aligned lateral distance of each predicted point to its GT line.

    Args:
      pred: f32[..., P, 2] predicted line (already matched to `gt`); gt: f32[..., P, 2].

    Returns:
      f32[..., P] distance from pred point k to the infinite line through gt points k and k+1 (k = P-1 uses P-2, P-1).
    """
    p = gt.shape[-2]
    k0 = jnp.minimum(jnp.arange(p), p - 2)
    a = jnp.take(gt, k0, axis=-2)
    b = jnp.take(gt, k0 + 1, axis=-2)
    return point_to_line_distance(pred, a, b)


def _paper_chamfer_sum(matched: jax.Array, gt: jax.Array, gt_valid: jax.Array) -> jax.Array:
    """matched, gt: f32[..., L, P, 2]; gt_valid: bool[..., L] -> f32[...] numerator of the official Chamfer."""
    m = gt_valid[..., :, None, None].astype(gt.dtype)
    pm, gm = matched * m, gt * m
    # d[..., i, j, k] = |pred line i point k - gt line j point k|^2
    d = jnp.sum((pm[..., :, None, :, :] - gm[..., None, :, :, :]) ** 2, axis=-1)
    pred_to_gt = jnp.min(d, axis=-2)  # [..., i, k]
    gt_to_pred = jnp.min(d, axis=-3)  # [..., j, k]
    lm = gt_valid[..., :, None]
    return jnp.sum(jnp.where(lm, pred_to_gt, 0.0), (-2, -1)) + jnp.sum(jnp.where(lm, gt_to_pred, 0.0), (-2, -1))


def set_chamfer(a: jax.Array, a_valid: jax.Array, b: jax.Array, b_valid: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Symmetric mean nearest-point (Chamfer) distance between two masked point sets, in metres.

    Args:
      a: f32[..., N, 2]; a_valid: bool[..., N]; b: f32[..., M, 2]; b_valid: bool[..., M].

    Returns:
      (f32[...] 0.5 * (mean_{a} min_{b} |a - b| + mean_{b} min_{a} |a - b|) over valid points,
       bool[...] whether both sets are non-empty; the distance is 0 where they are not).
    """
    dx = a[..., :, None, 0] - b[..., None, :, 0]  # x and y planes: fused, much faster than a trailing axis of 2
    dy = a[..., :, None, 1] - b[..., None, :, 1]
    d = jnp.sqrt(dx * dx + dy * dy)  # [..., N, M]
    big = jnp.asarray(jnp.inf, d.dtype)
    d = jnp.where(a_valid[..., :, None] & b_valid[..., None, :], d, big)
    return _chamfer_of_nearest(jnp.min(d, -1), a_valid, jnp.min(d, -2), b_valid)


def _chamfer_of_nearest(a2b, a_valid, b2a, b_valid):
    """`set_chamfer` from each point's distance to the other set: a2b f32[..., N], b2a f32[..., M]."""
    na = jnp.sum(a_valid, -1)
    nb = jnp.sum(b_valid, -1)
    ok = (na > 0) & (nb > 0)
    a2b = jnp.sum(jnp.where(a_valid, a2b, 0.0), -1) / jnp.maximum(na, 1)
    b2a = jnp.sum(jnp.where(b_valid, b2a, 0.0), -1) / jnp.maximum(nb, 1)
    return jnp.where(ok, 0.5 * (a2b + b2a), 0.0), ok


# ------------------------------------------------------------------------------------------ cut-invariant score
RECONSTRUCTION_THRESHOLDS_M = (0.5, 1.0, 1.5)  # the tolerances of the tokenizer's reconstruction figures
CONNECT_TOLERANCE_M = 0.5  # a GT line whose first point lies this close to another's last point is its successor


def threshold_key(t: float) -> str:
    """The suffix naming a threshold in sums and metrics: 0.5 -> "0.5", 1.0 -> "1"."""
    return f"{float(t):g}"


CUTFREE_SAMPLES = 2  # samples per polyline segment of the cut-invariant score (at (k + 0.5) / S of its length)
_CUTFREE_KEYS = ("cf_pred_len", "cf_pred_hit_len", "cf_gt_len", "cf_gt_hit_len", "cf_pred_dist_sum",
                 "cf_pred_dist_len", "cf_gt_dist_sum", "cf_gt_dist_len", "cf_pred_hit_dist_sum",
                 "cf_gt_hit_dist_sum", "cf_pred_hit_len_directed", "cf_gt_hit_len_directed")


def point_to_segments_distance(p: jax.Array, a: jax.Array, b: jax.Array, seg_valid: jax.Array) -> jax.Array:
    """Distance from each point to the nearest of a set of segments.

    Args:
      p: f32[N, 2] points; a, b: f32[M, 2] segment end points; seg_valid: bool[M].

    Returns:
      f32[N] min over valid segments of the distance from p to the closed segment [a, b] (inf if none is valid).
    """
    return _point_to_segments(p, a, b, seg_valid)[0]


def _point_to_segments(p: jax.Array, a: jax.Array, b: jax.Array, seg_valid: jax.Array,
                       p_dir: jax.Array | None = None) -> tuple[jax.Array, jax.Array | None]:
    """`point_to_segments_distance`, and with `p_dir` f32[N, 2] (each point's direction of travel) also the
    distance to the nearest valid segment running the same way (p_dir . (b - a) > 0), from the same pass."""
    d2, dd2 = _nearest_squared(p, a, b, seg_valid, p_dir)
    return jnp.sqrt(d2), None if dd2 is None else jnp.sqrt(dd2)


def _nearest_squared(p, a, b, seg_valid, p_dir=None):
    """`_point_to_segments` before the square roots: the squared distances (min over the segments)."""
    # x and y as separate [N, M] planes (not a trailing axis of 2): XLA fuses them into one loop, ~8x faster on CPU
    px, py = p[:, 0:1], p[:, 1:2]
    ax, ay = a[None, :, 0], a[None, :, 1]
    abx, aby = b[None, :, 0] - ax, b[None, :, 1] - ay
    den = abx * abx + aby * aby
    apx, apy = px - ax, py - ay
    t = jnp.clip((apx * abx + apy * aby) / jnp.where(den > 0, den, 1.0), 0.0, 1.0)
    dx, dy = apx - t * abx, apy - t * aby
    d2 = jnp.where(seg_valid[None], dx * dx + dy * dy, jnp.inf)
    if p_dir is None:
        return jnp.min(d2, -1), None
    same = p_dir[:, 0:1] * abx + p_dir[:, 1:2] * aby > 0
    return jnp.min(d2, -1), jnp.min(jnp.where(same, d2, jnp.inf), -1)


CUTFREE_BLOCK_LINES = 8  # lines per tile of `_tiled_nearest`


def _tiled_nearest(pair_min, p, p_line_valid, s, s_line_valid, block: int = CUTFREE_BLOCK_LINES):
    """Nearest-neighbour distances between two sets of points (or segments) grouped by line, visiting only the
    valid lines: the distances of the search over every pair (a min is exact in any order; to float32 rounding, as
    the compiler may arrange a tile's arithmetic differently) for a fraction of the work where most line slots are
    padding (about a third of them are valid in the decoded maps: 7x less time in the evaluation).

    Args:
      pair_min: (p tile, s tile, s valid bool[m']) -> tuple of f32[n'] squared distances, each the min over the
        tile's valid s; a tile is the arrays of `p` / `s` with their first two dims merged ([block * k, ...]).
      p: tuple of f32[Lp, n, ...] (points, directions, ...) line by line; p_line_valid: bool[Lp].
      s: tuple of f32[Ls, m, ...] line by line; s_line_valid: bool[Ls] (its points or segments are valid with it).

    Returns:
      tuple of f32[Lp, n]: the distances (square roots of `pair_min`'s minima over every valid s) of every point of
      a valid line; 0 for the points of invalid lines (not computed: their weights are 0 wherever they are summed).

    Both sets are sorted valid lines first and cut into tiles of `block` lines; two loops run over the tiles
    that hold valid lines only (dynamic trip counts; under `vmap` every frame runs to the longest one's, which
    still saves most of the work, and on a CPU a few frames vmapped together run faster than one at a time).
    """
    def tiles(x, order):  # [L, k, ...] -> valid-first, padded to whole tiles [L' / block, block * k, ...]
        x = x[order]
        x = jnp.pad(x, [(0, (-x.shape[0]) % block)] + [(0, 0)] * (x.ndim - 1))
        return x.reshape((x.shape[0] // block, block * x.shape[1]) + x.shape[2:])

    lp, n = p[0].shape[:2]
    po, so = jnp.argsort(~p_line_valid, stable=True), jnp.argsort(~s_line_valid, stable=True)
    pt, st = [tiles(x, po) for x in p], [tiles(x, so) for x in s]
    svt = tiles(jnp.broadcast_to(s_line_valid[:, None], s[0].shape[:2]), so)
    n_p = -(-jnp.sum(p_line_valid) // block)  # tiles holding valid lines
    n_s = -(-jnp.sum(s_line_valid) // block)
    k = len(jax.eval_shape(pair_min, [x[0] for x in pt], [x[0] for x in st], svt[0]))
    dtype = p[0].dtype

    def p_tile(i, acc):
        def s_tile(j, best):
            return tuple(jnp.minimum(a, b) for a, b in zip(best, pair_min([x[i] for x in pt], [x[j] for x in st],
                                                                          svt[j])))

        found = jax.lax.fori_loop(0, n_s, s_tile, (jnp.full(pt[0].shape[1], jnp.inf, dtype),) * k)
        return tuple(a.at[i].set(f) for a, f in zip(acc, found))

    d2 = jax.lax.fori_loop(0, n_p, p_tile, (jnp.full(pt[0].shape[:2], jnp.inf, dtype),) * k)
    back = jnp.argsort(po)  # the inverse permutation
    return tuple(jnp.where(p_line_valid[:, None], jnp.sqrt(x.reshape(-1, n)[:lp][back]), 0.0) for x in d2)


def _nearest_by_line(p, p_dir, p_line_valid, a, b, line_valid):
    """`_point_to_segments(p, a, b, seg_valid, p_dir)` for points and segments grouped by line (`_tiled_nearest`):
    p, p_dir f32[Lp, n, 2], p_line_valid bool[Lp]; a, b f32[Ls, m, 2] segment ends, line_valid bool[Ls] ->
    (distance, directed distance) f32[Lp, n], 0 for the points of invalid lines."""
    return _tiled_nearest(lambda pt, st, sv: _nearest_squared(pt[0], st[0], st[1], sv, pt[1]), (p, p_dir),
                          p_line_valid, (a, b), line_valid)


def _nearest_point_squared(pt, st, sv):
    """pair_min of `_tiled_nearest` between points: squared distance from each point of pt[0] f32[N, 2] to the
    nearest valid point of st[0] f32[M, 2] (x and y planes, as in `set_chamfer`)."""
    dx = pt[0][:, None, 0] - st[0][None, :, 0]
    dy = pt[0][:, None, 1] - st[0][None, :, 1]
    return (jnp.min(jnp.where(sv[None], dx * dx + dy * dy, jnp.inf), -1),)


def _set_chamfer_by_line(a: jax.Array, a_valid: jax.Array, b: jax.Array, b_valid: jax.Array
                         ) -> tuple[jax.Array, jax.Array]:
    """`set_chamfer` of the points of the valid lines of a f32[La, P, 2] (a_valid bool[La]) and of b f32[Lb, P, 2]
    (b_valid bool[Lb]), visiting only valid lines (`_tiled_nearest`)."""
    (a2b,) = _tiled_nearest(_nearest_point_squared, (a,), a_valid, (b,), b_valid)
    (b2a,) = _tiled_nearest(_nearest_point_squared, (b,), b_valid, (a,), a_valid)
    av = jnp.broadcast_to(a_valid[:, None], a.shape[:2]).reshape(-1)
    bv = jnp.broadcast_to(b_valid[:, None], b.shape[:2]).reshape(-1)
    return _chamfer_of_nearest(a2b.reshape(-1), av, b2a.reshape(-1), bv)


def _segment_samples(lines: jax.Array, line_valid: jax.Array, samples: int):
    """lines f32[L, P, 2], line_valid bool[L] -> (segment starts f32[L*(P-1), 2], ends, valid bool[L*(P-1)],
    sample points f32[L*(P-1)*S, 2], their weights f32[L*(P-1)*S] = segment length / S (0 where invalid), their
    segment's direction f32[L*(P-1)*S, 2] (end - start, the line's point order))."""
    a, b = lines[:, :-1], lines[:, 1:]  # [L, P-1, 2]
    seg_len = jnp.linalg.norm(b - a, axis=-1)
    sv = jnp.broadcast_to(line_valid[:, None], seg_len.shape)
    t = (jnp.arange(samples, dtype=lines.dtype) + 0.5) / samples  # [S]
    pts = a[..., None, :] + t[:, None] * (b - a)[..., None, :]  # [L, P-1, S, 2]
    w = jnp.where(sv, seg_len, 0.0)[..., None] / samples * jnp.ones((samples,), lines.dtype)
    direction = jnp.broadcast_to((b - a)[..., None, :], pts.shape)
    return (a.reshape(-1, 2), b.reshape(-1, 2), sv.reshape(-1), pts.reshape(-1, 2), w.reshape(-1),
            direction.reshape(-1, 2))


def cutfree_frame_sums(pred: jax.Array, pred_exists: jax.Array, gt: jax.Array, gt_valid: jax.Array, *,
                       threshold: float = 1.5, samples: int = CUTFREE_SAMPLES,
                       extra_thresholds: tuple[float, ...] = ()) -> dict[str, jax.Array]:
    """Sums of the cut-invariant map score of one frame (no matching, no point order).

    Both line sets are taken as the union of their segments. Every segment is sampled at `samples` evenly spaced
    points, each weighted by the arc length it stands for (segment length / samples), so the sums are lengths:
    how a road is cut into lines (where lines start and end, how many) does not change them, only the geometry.

    Args:
      pred: f32[Q, P, 2] decoded lines; pred_exists: bool[Q] (logit > 0).
      gt: f32[L, P, 2] GT lines; gt_valid: bool[L].
      threshold: metres; a sample counts as a hit when its distance to the other set's segments is <= threshold
        (a point exactly on the other set is a hit, unlike the paper's F1).
      extra_thresholds: more thresholds (metres) whose hit lengths are added as "cf_pred_hit_len@T" and
        "cf_gt_hit_len@T" (T formatted with `threshold_key`): the same distances, other tolerances.

    Returns:
      {key: f32[]} for `_CUTFREE_KEYS`: predicted / GT length, the length within the threshold of the other set
      (*_directed: of a segment of the other set running the same way),
      length-weighted distance sums to the other set (counted only when both sets are non-empty, with the length
      they cover in *_dist_len), and the same distance sums restricted to the hits.
    """
    pa, pb, _, pp, pw, pdir = _segment_samples(pred, pred_exists, samples)
    ga, gb, _, gp, gw, gdir = _segment_samples(gt, gt_valid, samples)
    by_line = lambda x, lines: x.reshape((lines.shape[0], -1, 2))  # noqa: E731  (the flat arrays are line-major)
    # predicted samples -> GT segments, GT samples -> predicted segments (invalid lines' samples: 0, weight 0)
    d_pred, dd_pred = _nearest_by_line(by_line(pp, pred), by_line(pdir, pred), pred_exists, by_line(ga, gt),
                                       by_line(gb, gt), gt_valid)
    d_gt, dd_gt = _nearest_by_line(by_line(gp, gt), by_line(gdir, gt), gt_valid, by_line(pa, pred),
                                   by_line(pb, pred), pred_exists)
    d_pred, dd_pred, d_gt, dd_gt = (x.reshape(-1) for x in (d_pred, dd_pred, d_gt, dd_gt))
    both = jnp.any(pred_exists) & jnp.any(gt_valid)
    hit_p, hit_g = d_pred <= threshold, d_gt <= threshold
    fin_p = jnp.where(both, d_pred, 0.0)
    fin_g = jnp.where(both, d_gt, 0.0)
    extra = {}
    for t in extra_thresholds:
        extra["cf_pred_hit_len@" + threshold_key(t)] = jnp.sum(jnp.where(d_pred <= t, pw, 0.0))
        extra["cf_gt_hit_len@" + threshold_key(t)] = jnp.sum(jnp.where(d_gt <= t, gw, 0.0))
    return extra | {
        "cf_pred_len": jnp.sum(pw), "cf_pred_hit_len": jnp.sum(jnp.where(hit_p, pw, 0.0)),
        "cf_gt_len": jnp.sum(gw), "cf_gt_hit_len": jnp.sum(jnp.where(hit_g, gw, 0.0)),
        "cf_pred_dist_sum": jnp.sum(pw * fin_p), "cf_pred_dist_len": jnp.where(both, jnp.sum(pw), 0.0),
        "cf_gt_dist_sum": jnp.sum(gw * fin_g), "cf_gt_dist_len": jnp.where(both, jnp.sum(gw), 0.0),
        "cf_pred_hit_dist_sum": jnp.sum(jnp.where(hit_p, pw * fin_p, 0.0)),
        "cf_gt_hit_dist_sum": jnp.sum(jnp.where(hit_g, gw * fin_g, 0.0)),
        "cf_pred_hit_len_directed": jnp.sum(jnp.where(dd_pred <= threshold, pw, 0.0)),
        "cf_gt_hit_len_directed": jnp.sum(jnp.where(dd_gt <= threshold, gw, 0.0)),
    }


def reduce_cutfree(s: dict[str, np.ndarray]) -> dict[str, float]:
    """Cut-invariant sums (f32[S] per key, S steps) -> {map_f1_cutfree, map_precision_cutfree, map_recall_cutfree,
    map_chamfer_cutfree, map_chamfer_within_cutfree} + {map_f1_cutfree_directed, map_precision_cutfree_directed,
    map_recall_cutfree_directed} when the sums carry the directed hits, each the mean over the steps where it is
    defined (NaN if none).

    precision = predicted length within the threshold of the GT / predicted length; recall = GT length within
    the threshold of the prediction / GT length; F1 = 2PR/(P+R) (0 when one of them is 0);
    chamfer = 0.5 (mean distance of predicted arc length to the GT + mean distance of GT arc length to the
    prediction), metres, over frames with both sets non-empty; chamfer_within = the same means over the arc
    length within the threshold only (how close what is found is). The *_directed scores count a sample as a hit
    only where a segment of the other set within the threshold runs the same way (positive dot product of the
    segment directions, in point order): the cut still does not matter, the direction does; the gap to the plain
    cut-free score is the length found but decoded the wrong way round.
    """
    s = {k: np.asarray(v, np.float64) for k, v in s.items()}

    def ratio(num, den):
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)

    prec = ratio(s["cf_pred_hit_len"], s["cf_pred_len"])
    rec = ratio(s["cf_gt_hit_len"], s["cf_gt_len"])
    cham = 0.5 * (ratio(s["cf_pred_dist_sum"], s["cf_pred_dist_len"]) + ratio(s["cf_gt_dist_sum"], s["cf_gt_dist_len"]))
    within = 0.5 * (ratio(s["cf_pred_hit_dist_sum"], s["cf_pred_hit_len"])
                    + ratio(s["cf_gt_hit_dist_sum"], s["cf_gt_hit_len"]))

    def mean(x):
        x = x[~np.isnan(x)]
        return float(x.mean()) if x.size else float("nan")

    def f1_of(prec, rec):
        p0, r0 = np.nan_to_num(prec), np.nan_to_num(rec)
        return np.where(np.isnan(prec) & np.isnan(rec), np.nan, np.nan_to_num(ratio(2 * p0 * r0, p0 + r0)))

    out = {"map_f1_cutfree": mean(f1_of(prec, rec)), "map_precision_cutfree": mean(prec),
           "map_recall_cutfree": mean(rec), "map_chamfer_cutfree": mean(cham), "map_chamfer_within_cutfree": mean(within)}
    for k in s:
        if k.startswith("cf_pred_hit_len@"):
            t = k.split("@", 1)[1]
            out["map_f1_cutfree@" + t] = mean(f1_of(ratio(s[k], s["cf_pred_len"]),
                                                    ratio(s["cf_gt_hit_len@" + t], s["cf_gt_len"])))
    if "cf_pred_hit_len_directed" in s:  # sums made before the directed hits existed lack them
        dprec = ratio(s["cf_pred_hit_len_directed"], s["cf_pred_len"])
        drec = ratio(s["cf_gt_hit_len_directed"], s["cf_gt_len"])
        out.update({"map_f1_cutfree_directed": mean(f1_of(dprec, drec)), "map_precision_cutfree_directed": mean(dprec),
                    "map_recall_cutfree_directed": mean(drec)})
    return out


def map_metric_sums(pred_points: jax.Array, pred_logits: jax.Array, gt_points: jax.Array, gt_valid: jax.Array, *,
                    threshold: float = 1.5, step_axis: int | None = None,
                    count_exact_hits: bool | jax.Array = False,
                    length_edges: tuple[float, ...] | None = None, window_half: float | None = None,
                    cutfree: bool = True, cutfree_samples: int = CUTFREE_SAMPLES,
                    extra_thresholds: tuple[float, ...] = (), connectivity: bool = False) -> dict[str, jax.Array]:
    """Sums and counts of the map metrics for a batch of decoded frames.

    Args:
      pred_points: f32[..., Q, P, 2] decoded lines (Q = 50, P = 20 in the paper), metres, in the frame's ego frame.
      pred_logits: f32[..., Q] existence logits.
      gt_points: f32[..., L, P, 2] GT lines (L = Q); gt_valid: bool[..., L].
      threshold: F1 distance threshold in metres (1.5 in the paper).
      count_exact_hits: False (paper) counts a point as TP only when 0 < d <= threshold, so a point predicted
        exactly on the GT is not a TP (identical lines score F1 = 0); True counts 0 <= d <= threshold. Or
        bool[...] (broadcast against the leading dims): which frames count exact hits (frames of both kinds in
        one call; not with `map_metrics`, whose jit takes it as a static argument).
      step_axis: index (in the leading dims `...`, e.g. 1 for [B, T_future, ...]) of the future-step axis to keep,
        so that ratios are formed per step and then averaged over steps, as the official code does; None pools
        every frame as one step.
      length_edges: ascending GT line lengths (metres, e.g. `LENGTH_EDGES_M`) that split the GT lines into
        len + 1 groups; adds the sums of the recall-by-length diagnostic ("length_tp", "length_gt": f32[S, G]).
      window_half: the half size of the frames' square window (32 m for SLEDGE lanes); adds the sums of the
        recall-by-ends diagnostic ("ends_tp", "ends_gt": f32[S, 3], GT lines by how many ends lie more than
        `BORDER_TOLERANCE_M` inside the window).
      cutfree: also the sums of the cut-invariant score (`cutfree_frame_sums` at the same threshold, keys "cf_*"),
        reported beside the paper's F1 as map_f1_cutfree etc.; cutfree_samples: its samples per segment.
      extra_thresholds: more thresholds (metres) of the paper's F1 ("tp@T") and of the cut-invariant one
        (`cutfree_frame_sums`'s "cf_*_hit_len@T"): map_f1@T and map_f1_cutfree@T.
      connectivity: adds "conn_pairs" (GT successor pairs: two valid GT lines, the first point of one within
        `CONNECT_TOLERANCE_M` of the last point of the other) and "conn_kept" (those whose Hungarian-matched
        predictions both exist and still join: last point to first point within `threshold`): map_connectivity,
        the share of successor pairs the reconstruction keeps.

    Returns:
      {key: f32[S]} with S the step-axis length (1 if None); feed to `reduce_map_metrics`.
    """
    matched, matched_logits, _ = match_lines(pred_points, pred_logits, gt_points, gt_valid)
    gv = gt_valid
    pred_exists = pred_logits > 0  # [..., Q]
    matched_exists = matched_logits > 0  # [..., L]
    p = gt_points.shape[-2]

    d = jnp.linalg.norm(matched - gt_points, axis=-1)  # [..., L, P]
    both = (matched_exists & gv)[..., None]
    if isinstance(count_exact_hits, bool):
        lower = (d >= 0) if count_exact_hits else (d > 0)
    else:  # per frame
        lower = (d > 0) | (jnp.asarray(count_exact_hits, bool)[..., None, None] & (d >= 0))
    tp_mask = both & lower & (d <= threshold)
    tp_line = jnp.sum(tp_mask, -1).astype(jnp.float32)  # [..., L]
    tp = jnp.sum(tp_line, -1)
    n_pred = jnp.sum(pred_exists, -1).astype(jnp.float32)
    n_gt = jnp.sum(gv, -1).astype(jnp.float32)
    lat = jnp.sum(jnp.where(tp_mask, lateral_distances(matched, gt_points), 0.0), (-2, -1))
    lead_shape = tp.shape

    def chamfers(args):  # one frame: [L, P, 2] ... -> (paper numerator, corrected Chamfer, both sets non-empty)
        m, g, v, pp, pe = args
        cc, ok = _set_chamfer_by_line(pp, pe, g, v)
        return _paper_chamfer_sum(m, g, v), cc, ok

    # Frames in chunks (vmapped inside lax.map) keep the pairwise distances small for big batches.
    n = int(np.prod(lead_shape))
    frames = lambda x, k: x.reshape((n,) + x.shape[x.ndim - k:])
    cham, cc, ok = jax.lax.map(chamfers, (frames(matched, 3), frames(gt_points, 3), frames(gv, 1),
                                          frames(pred_points, 3), frames(pred_exists, 1)),
                               batch_size=min(n, 4))
    cham, cc, ok = (x.reshape(lead_shape) for x in (cham, cc, ok))

    per_frame = {
        "tp": tp, "fp": p * n_pred - tp, "fn": p * n_gt - tp, "lateral_sum": lat,
        "chamfer_sum": cham, "chamfer_den": 2.0 * p * n_gt,
        "chamfer_corrected_sum": cc, "chamfer_corrected_count": ok.astype(jnp.float32),
        "chamfer_corrected_skipped": (~ok).astype(jnp.float32),
    }
    for t in extra_thresholds:
        per_frame["tp@" + threshold_key(t)] = jnp.sum(both & lower & (d <= t), (-2, -1)).astype(jnp.float32)
    if connectivity:
        per_frame["conn_pairs"], per_frame["conn_kept"] = _successor_pairs(matched, matched_exists, gt_points, gv,
                                                                           threshold)
    lead = tp.ndim

    def reduce(x, groups: int = 0):  # sum over the leading dims but the step axis; keep `groups` trailing dims
        x = x.astype(jnp.float32)
        tail = x.shape[x.ndim - groups:]
        if step_axis is None:
            return jnp.sum(x.reshape((-1,) + tail), 0)[None]
        x = jnp.moveaxis(x, step_axis % lead if lead else 0, 0)
        return jnp.sum(x.reshape((x.shape[0], -1) + tail), 1)

    if cutfree:
        cf = jax.lax.map(lambda a: cutfree_frame_sums(*a, threshold=threshold, samples=cutfree_samples,
                                                      extra_thresholds=extra_thresholds),
                         (frames(pred_points, 3), frames(pred_exists, 1), frames(gt_points, 3), frames(gv, 1)),
                         batch_size=min(n, 4))
        per_frame.update({k: v.reshape(lead_shape) for k, v in cf.items()})
    out = {k: reduce(v) for k, v in per_frame.items()}

    def recall_groups(name, group, num_groups):  # TP and GT points of the GT lines in each group i32[..., L]
        onehot = jax.nn.one_hot(group, num_groups) * gv[..., None]  # [..., L, G]
        out[name + "_tp"] = reduce(jnp.einsum("...l,...lg->...g", tp_line, onehot), groups=1)
        out[name + "_gt"] = reduce(p * jnp.sum(onehot, -2), groups=1)

    if length_edges is not None:
        glen = jnp.sum(jnp.linalg.norm(jnp.diff(gt_points, axis=-2), axis=-1), -1)  # [..., L]
        recall_groups("length", jnp.searchsorted(jnp.asarray(length_edges, glen.dtype), glen, side="right"),
                      len(length_edges) + 1)
    if window_half is not None:
        inside = jnp.max(jnp.abs(gt_points[..., (0, -1), :]), -1) < window_half - BORDER_TOLERANCE_M  # [..., L, 2]
        recall_groups("ends", jnp.sum(inside, -1), len(END_LABELS))
    return out


def _successor_pairs(matched, matched_exists, gt, gt_valid, threshold: float):
    """(GT successor pairs f32[...], those kept f32[...]) per frame; see `map_metric_sums`'s `connectivity`.
    matched f32[..., L, P, 2] the predictions matched to the GT slots, matched_exists bool[..., L]."""
    gap = lambda x: jnp.linalg.norm(x[..., :, None, -1, :] - x[..., None, :, 0, :], axis=-1)  # [..., L, L] i -> j
    n = gt.shape[-3]
    pair = (gt_valid[..., :, None] & gt_valid[..., None, :] & ~jnp.eye(n, dtype=bool)
            & (gap(gt) <= CONNECT_TOLERANCE_M))
    kept = pair & matched_exists[..., :, None] & matched_exists[..., None, :] & (gap(matched) <= threshold)
    return jnp.sum(pair, (-2, -1)).astype(jnp.float32), jnp.sum(kept, (-2, -1)).astype(jnp.float32)


def reduce_map_metrics(sums: dict[str, jax.Array]) -> dict[str, float]:
    """Sums -> {map_f1, map_precision, map_recall, map_lateral, map_chamfer, map_chamfer_corrected,
    map_chamfer_corrected_skipped} (+ map_recall_by_length and map_gt_points_by_length, lists over the length
    groups, and map_recall_by_ends / map_gt_points_by_ends over `END_LABELS`, when the sums have them; + the
    cut-invariant map_*_cutfree of `reduce_cutfree` when they have its "cf_*" sums).

    Per step: precision = TP/(TP+FP), recall = TP/(TP+FN), F1 = 2TP/(2TP+FP+FN) (= 2PR/(P+R)), lateral = sum/TP,
    Chamfer = sum/(2 P #GT lines), corrected Chamfer = mean over frames with both sets non-empty. Each is then the
    mean over the steps where it is defined (NaN if none). `map_chamfer_corrected_skipped` is a count.
    """
    s = {k: np.asarray(v, np.float64) for k, v in sums.items()}

    def ratio(num, den):
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)

    prec = ratio(s["tp"], s["tp"] + s["fp"])
    rec = ratio(s["tp"], s["tp"] + s["fn"])
    # 2PR/(P+R) written as 2TP/(2TP+FP+FN): equal where P and R are defined, 0 (not NaN) when nothing is predicted.
    f1 = ratio(2 * s["tp"], 2 * s["tp"] + s["fp"] + s["fn"])

    def mean(x):
        x = x[~np.isnan(x)]
        return float(x.mean()) if x.size else float("nan")

    def groups(name):  # the recall diagnostic of `map_metric_sums`'s groups "length" / "ends", pooled over steps
        tp, gt = s[name + "_tp"].sum(0), s[name + "_gt"].sum(0)
        return {f"map_recall_by_{name}": [float(x) for x in ratio(tp, gt)],
                f"map_gt_points_by_{name}": [float(x) for x in gt]}

    return {
        "map_f1": mean(f1),
        "map_precision": mean(prec),
        "map_recall": mean(rec),
        "map_lateral": mean(ratio(s["lateral_sum"], s["tp"])),
        "map_chamfer": mean(ratio(s["chamfer_sum"], s["chamfer_den"])),
        "map_chamfer_corrected": mean(ratio(s["chamfer_corrected_sum"], s["chamfer_corrected_count"])),
        "map_chamfer_corrected_skipped": float(s["chamfer_corrected_skipped"].sum()),
        **{k: v for name in ("length", "ends") if name + "_tp" in s for k, v in groups(name).items()},
        **(reduce_cutfree({k: s[k] for k in s if k.startswith("cf_")}) if "cf_pred_len" in s else {}),
        **{"map_f1@" + k[3:]: mean(ratio(2 * s[k], s["tp"] + s["fp"] + s["tp"] + s["fn"]))
           for k in s if k.startswith("tp@")},  # TP + FP and TP + FN do not depend on the threshold
        **({"map_connectivity": mean(ratio(s["conn_kept"], s["conn_pairs"])),
            "map_successor_pairs": float(s["conn_pairs"].sum())} if "conn_pairs" in s else {}),
    }


_map_metric_sums_jit = jax.jit(map_metric_sums, static_argnames=("threshold", "step_axis", "count_exact_hits",
                                                                 "length_edges", "window_half", "cutfree",
                                                                 "cutfree_samples", "extra_thresholds",
                                                                 "connectivity"))


def map_metrics(*args, **kwargs) -> dict[str, float]:
    """`reduce_map_metrics(map_metric_sums(...))` for one batch (same arguments as `map_metric_sums`), jitted."""
    return reduce_map_metrics(_map_metric_sums_jit(*args, **kwargs))
