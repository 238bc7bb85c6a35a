"""Coarse-to-fine correspondence (paper 3.1).

1. Each detail strand goes to the guide with the smallest integrated squared distance, eq. (1):
   d(d_j, g_i) = sum_k |d_jk - prox(d_jk, g_i)|^2, prox the closest point on the guide polyline.
2. Each guide is sampled with tracking points p_jk: equidistantly in arc length (the paper;
   ``tracking.point_placement: arc_length``), or (``hair_mass``, the default) at the arc
   lengths that split the free hair mass of the guide's strands, projected onto the guide
   (closest points), into equal parts: point k at the (k + 1/2) / P quantile (midpoint rule).
   Equidistant points can sit where there is no hair (near the root, where the first free
   vertex is an edge away, or past the tips of hair shorter than its guide) and leave their
   clusters empty; at the mass quantiles each point has hair around it, so a cluster is empty
   only when the hair has fewer distinct heights than tracking points.
3. Each detail strand is split into segments s_ik: its vertices closest to p_jk among the
   tracking points of its guide.  A cluster C_jk is the union of segments s_ik over the strands
   of guide j.  Only free (non-root) vertices join clusters: root vertices are prescribed by the
   body and cannot be steered.  Empty clusters are dropped with a warning that names them.

Soft assignment (``tracking.assignment: soft``; the paper's section 5 / Fig. 8 names it as
future work, it is not in the paper): step 1 gives each strand a weight per guide instead of
one guide.  With D_sg^2 = d(d_s, g_g) / n_s the mean squared distance of eq. (1) (m^2) and
D_s^2 = min_g D_sg^2, a softmax of -eq. (1):

    w_sg = exp(-(D_sg^2 - D_s^2) / b^2) / sum_h exp(-(D_sh^2 - D_s^2) / b^2),

b = ``tracking.blend_width`` (m): a guide whose mean squared distance exceeds the nearest
one's by b^2 gets e^-1 of its weight; raw weights below ``WEIGHT_CUTOFF`` are set to 0 before
the normalisation (an excess above 6.9 b^2).  For a strand at z between two guides at -a and +a
the share of the guide at +a is the logistic 1 / (1 + exp(-4 a z / b^2)): it changes over
|z| ~ b^2 / (4 a) and keeps changing past the guides, so the shares vary across the whole wisp
when b is about the guides' spacing.  (A Gaussian of the excess RMS distance, tried first, is
flat past the guides: every strand outside them got the same shares.)  Step 2 weighs each
vertex's mass by its strand's weight for the guide.  Step 3 is done for every guide the strand
has weight on: each free vertex joins, per such guide g, the cluster of g's tracking point
nearest to it, with the strand's weight w_sg; a vertex's weights sum to one.  Hard assignment is the limit b -> 0 (one-hot weights).  The
memberships are kept as triples (vertex, cluster, weight): ``member_vertex``,
``member_cluster``, ``member_weight``; ``cluster_of_vertex`` is then each vertex's cluster of
largest weight (its dominant cluster).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from hairexp.errors import InputError, real_array, whole_array

log = logging.getLogger(__name__)

#: soft assignment: a strand's raw guide weight below this (its excess mean squared distance > 6.9 b^2) is 0
WEIGHT_CUTOFF = 1e-3
ASSIGNMENTS = ("hard", "soft")
PLACEMENTS = ("hair_mass", "arc_length")


def closest_points_on_polyline(X: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Closest points on polyline P (n, 3) to points X (m, 3): (points (m, 3), arc length (m,))."""
    if len(P) < 2:   # numpy's "argmin of an empty sequence" named nothing (probe of issue 12, round 12)
        raise InputError(f"the polyline needs >= 2 points, got {len(P)}", "closest_points_on_polyline")
    a, b = P[:-1], P[1:]
    ab = b - a                                        # (n-1, 3)
    L = np.einsum("ij,ij->i", ab, ab)
    u = np.einsum("mij,ij->mi", X[:, None, :] - a[None], ab) / L
    u = np.clip(u, 0.0, 1.0)                          # (m, n-1)
    Q = a[None] + u[..., None] * ab[None]             # (m, n-1, 3)
    d2 = np.sum((X[:, None, :] - Q) ** 2, axis=-1)
    j = np.argmin(d2, axis=1)
    seg_len = np.sqrt(L)
    s0 = np.concatenate([[0.0], np.cumsum(seg_len)])
    rows = np.arange(len(X))
    return Q[rows, j], s0[j] + u[rows, j] * seg_len[j]


@dataclass(frozen=True)
class Correspondence:
    """guide_of_strand (S,) (soft: the guide of largest weight), tracking points (G, P, 3) with
    their arc lengths (P,) per guide, cluster_of_vertex (V,) (-1: in no cluster; soft: the
    dominant cluster), cluster_guide (K,), cluster_point (K,); the memberships as triples
    member_vertex (E,), member_cluster (E,), member_weight (E,) (hard: one per clustered free
    vertex, weight 1, in vertex order) and guide_weights (S, G) (hard: one-hot)."""

    guide_of_strand: np.ndarray
    tracking_points: np.ndarray
    tracking_arclength: np.ndarray
    cluster_of_vertex: np.ndarray
    cluster_guide: np.ndarray
    cluster_point: np.ndarray
    member_vertex: np.ndarray = None
    member_cluster: np.ndarray = None
    member_weight: np.ndarray = None
    guide_weights: np.ndarray = None

    @property
    def n_clusters(self) -> int:
        return len(self.cluster_guide)


def sample_tracking_points(P: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points equidistant in arc length at the centres of equal intervals."""
    check_correspondence_options(count, "arc_length", "hard")   # -1 or 2.5 gave points without a word
    if len(P) < 2:
        raise InputError(f"the polyline needs >= 2 points, got {len(P)}", "sample_tracking_points")
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    targets = (np.arange(count) + 0.5) / count * s[-1]
    pts = np.stack([np.interp(targets, s, P[:, c]) for c in range(3)], axis=1)
    return pts, targets


def mass_tracking_points(P: np.ndarray, count: int, X: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``count`` points on the polyline P at the (k + 1/2) / count quantiles of the arc lengths
    of the closest guide points of the hair vertices X (m, 3), weighted by w (m,) (their mass
    times their share of this guide); equidistant (``sample_tracking_points``) when w is empty."""
    keep = w > 0
    if not keep.any():
        return sample_tracking_points(P, count)
    _, arc = closest_points_on_polyline(X[keep], P)
    o = np.argsort(arc, kind="stable")
    arc, ww = arc[o], w[keep][o]
    c = np.cumsum(ww)
    mid = (c - 0.5 * ww) / c[-1]                       # midpoint rule: each vertex's mass centred on it
    targets = np.interp((np.arange(count) + 0.5) / count, mid, arc)
    seg = np.linalg.norm(np.diff(P, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    pts = np.stack([np.interp(targets, s, P[:, k]) for k in range(3)], axis=1)
    return pts, targets


def strand_guide_distances(detail_rest: np.ndarray, offsets: np.ndarray, guides_rest: list[np.ndarray]) -> np.ndarray:
    """(S, G) eq. (1): the integrated squared distance of each strand's vertices to each guide."""
    S = len(offsets) - 1
    strand = np.repeat(np.arange(S), np.diff(offsets))
    dist = np.zeros((S, len(guides_rest)))
    for g, P in enumerate(guides_rest):
        Q, _ = closest_points_on_polyline(detail_rest, P)
        dist[:, g] = np.bincount(strand, weights=np.sum((detail_rest - Q) ** 2, axis=1), minlength=S)
    return dist


def soft_guide_weights(dist: np.ndarray, counts: np.ndarray, blend_width: float) -> np.ndarray:
    """(S, G) the soft guide weights of the strands (module docstring) from eq. (1) ``dist``
    (S, G) and the strands' vertex counts (S,); rows sum to one."""
    if not (np.isfinite(blend_width) and blend_width > 0):
        raise InputError(f"must be > 0 (m), got {blend_width}", "tracking.blend_width")
    D2 = np.maximum(dist, 0.0) / counts[:, None]
    w = np.exp(-(D2 - D2.min(axis=1, keepdims=True)) / blend_width ** 2)
    w[w < WEIGHT_CUTOFF] = 0.0
    return w / w.sum(axis=1, keepdims=True)


def check_correspondence_options(points_per_guide, placement: str, assignment: str) -> None:
    """InputError naming the key for a tracking option the correspondence cannot use (also
    called by hairexp/app/validate.py: an experiment checks every variant before the first runs)."""
    if placement not in PLACEMENTS:
        raise InputError(f"unknown placement {placement!r} (hair_mass|arc_length)", "tracking.point_placement")
    if assignment not in ASSIGNMENTS:
        raise InputError(f"unknown assignment {assignment!r} (hard|soft)", "tracking.assignment")
    if isinstance(points_per_guide, bool) or not isinstance(points_per_guide, (int, np.integer)) or points_per_guide < 1:
        raise InputError(f"must be an integer >= 1, got {points_per_guide!r}", "tracking.points_per_guide")


def build_correspondence(detail_rest: np.ndarray, offsets: np.ndarray, free: np.ndarray,
                         guides_rest: list[np.ndarray], points_per_guide: int,
                         max_distance: float = 0.0, assignment: str = "hard",
                         blend_width: float = 0.01, placement: str = "hair_mass",
                         masses: np.ndarray | None = None) -> Correspondence:
    """``max_distance`` > 0: a strand whose RMS distance to every guide (eq. 1 over its vertex
    count) exceeds it cannot be claimed by any guide, and is an error naming the strand.
    ``assignment``: ``hard`` (paper 3.1) or ``soft`` with ``blend_width`` b in metres (module
    docstring).  ``placement``: ``hair_mass`` or ``arc_length`` (step 2); ``masses`` (V,)
    the vertex masses it weighs (None: all equal)."""
    check_correspondence_options(points_per_guide, placement, assignment)
    if not guides_rest:
        raise InputError("a tracked run needs at least one guide", "guides")
    G = len(guides_rest)
    detail_rest = real_array(detail_rest, "build_correspondence detail_rest")
    if detail_rest.ndim != 2 or detail_rest.shape[1] != 3 or not np.isfinite(detail_rest).all():
        raise InputError(f"the detail hair must be finite points of shape (V, 3), got shape {detail_rest.shape}",
                         "build_correspondence detail_rest")
    V = len(detail_rest)
    offsets = whole_array(offsets, "build_correspondence offsets").reshape(-1)
    if offsets.size < 2 or offsets[0] != 0 or offsets[-1] != V or np.any(np.diff(offsets) < 1):
        raise InputError(f"must start at 0, increase strictly and end at the {V} detail vertices, got "
                         f"{offsets[:6].tolist()}{' ...' if offsets.size > 6 else ''} (length {offsets.size})",
                         "build_correspondence offsets")
    free = np.asarray(free)
    if free.shape != (V,) or free.dtype != bool:
        raise InputError(f"must be a boolean mask of shape ({V},), got {free.dtype} {free.shape}",
                         "build_correspondence free")
    if masses is not None:
        masses = real_array(masses, "build_correspondence masses")
        if masses.shape != (V,) or not (np.isfinite(masses).all() and (masses >= 0).all()):
            raise InputError(f"must be {V} finite numbers >= 0 (kg), got shape {masses.shape}"
                             + ("" if masses.shape != (V,) else f", min {masses.min():g}"), "build_correspondence masses")
    if not (np.isfinite(max_distance) and max_distance >= 0):
        raise InputError(f"must be a finite number >= 0 (m), got {max_distance}", "tracking.max_guide_distance")
    for g, P in enumerate(guides_rest):   # named here: they came out as "non-finite distance" (probe of issue 12)
        P = real_array(P, f"guides: guide {g}")
        if P.ndim != 2 or P.shape[1] != 3 or len(P) < 2:
            raise InputError(f"guide {g} must be a polyline of >= 2 points of shape (n, 3), got shape {P.shape}",
                             "guides")
        if not np.isfinite(P).all():
            raise InputError(f"guide {g} has a non-finite point", "guides")
        short = np.flatnonzero(np.linalg.norm(np.diff(P, axis=0), axis=1) <= 0.0)
        if short.size:
            raise InputError(f"guide {g} has a zero-length edge (points {int(short[0])} and {int(short[0]) + 1} "
                             "coincide)", "guides")
    # 1. eq. (1): integrated squared distance of each strand to each guide
    dist = strand_guide_distances(detail_rest, offsets, guides_rest)
    strand = np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))
    if not np.isfinite(dist).all():
        raise InputError("non-finite distance between detail hair and guides", "guides")
    guide_of_strand = np.argmin(dist, axis=1)
    if max_distance > 0:
        rms = np.sqrt(dist.min(axis=1) / np.diff(offsets))
        far = np.flatnonzero(rms > max_distance)
        if far.size:
            s0 = int(far[0])
            raise InputError(f"strand {s0} is {rms[s0]:.4g} m (RMS) from the nearest guide, more than "
                             f"tracking.max_guide_distance={max_distance}; no guide can claim it "
                             f"({far.size} such strands)", "tracking.max_guide_distance")
    # the strands' guide weights (soft: module docstring; hard: one-hot)
    if assignment == "hard":
        gw = np.zeros_like(dist)
        gw[np.arange(len(gw)), guide_of_strand] = 1.0
    else:
        gw = soft_guide_weights(dist, np.diff(offsets), float(blend_width))
        guide_of_strand = np.argmax(gw, axis=1)
    # 2. tracking points
    if placement == "arc_length":
        tp, tp_s = zip(*(sample_tracking_points(P, points_per_guide) for P in guides_rest))
    else:
        m = np.ones(len(detail_rest)) if masses is None else np.asarray(masses, dtype=np.float64)
        mf = np.where(free, m, 0.0)
        tp, tp_s = zip(*(mass_tracking_points(P, points_per_guide, detail_rest, mf * gw[strand, g])
                         for g, P in enumerate(guides_rest)))
    tracking = np.stack(tp)
    # 3. segments: nearest tracking point of the strand's own guide (soft: of each guide it has weight on)
    if assignment == "hard":
        gv = guide_of_strand[strand]
        d2 = np.sum((detail_rest[:, None, :] - tracking[gv]) ** 2, axis=-1)   # (V, P)
        point_of_vertex = np.argmin(d2, axis=1)
        raw = gv * points_per_guide + point_of_vertex
        raw = np.where(free, raw, -1)
        mv = np.flatnonzero(raw >= 0)
        mraw, mw = raw[mv], np.ones(mv.size)
    else:
        vs, mvs, mws = [], [], []
        fv = np.flatnonzero(free)
        for g in range(G):
            on = fv[gw[strand[fv], g] > 0]
            d2 = np.sum((detail_rest[on][:, None, :] - tracking[g][None]) ** 2, axis=-1)
            vs.append(on)
            mvs.append(g * points_per_guide + np.argmin(d2, axis=1))
            mws.append(gw[strand[on], g])
        mv, mraw, mw = (np.concatenate(a) for a in (vs, mvs, mws))
        order = np.lexsort((mraw, mv))             # vertex order, then cluster
        mv, mraw, mw = mv[order], mraw[order], mw[order]
        # the dominant cluster of each free vertex (largest weight; ties: the first guide)
        raw = np.full(len(detail_rest), -1)
        best = np.full(len(detail_rest), -1.0)
        for v, k, w in zip(mv, mraw, mw):
            if w > best[v]:
                best[v], raw[v] = w, k
    counts = np.bincount(mraw, minlength=G * points_per_guide)
    kept = np.flatnonzero(counts > 0)
    empty = np.flatnonzero(counts == 0)
    if empty.size:   # one line, however many (it was a line each: ~1,000 with 256 points a guide; probe of issue 12)
        shown = ", ".join(f"guide {k // points_per_guide} point {k % points_per_guide}" for k in empty[:8])
        more = f" and {empty.size - 8} more" if empty.size > 8 else ""
        log.warning("%d of %d clusters are empty (no free detail vertex is closest to their tracking point) and are "
                    "dropped: %s%s", empty.size, counts.size, shown, more)
    if kept.size == 0:
        raise InputError("every cluster is empty: no free detail vertex is near a tracking point", "tracking")
    remap = np.full(G * points_per_guide, -1)
    remap[kept] = np.arange(kept.size)
    cluster_of_vertex = np.where(raw >= 0, remap[np.maximum(raw, 0)], -1)
    return Correspondence(guide_of_strand, tracking, np.stack(tp_s), cluster_of_vertex,
                          kept // points_per_guide, kept % points_per_guide,
                          mv, remap[mraw], mw, gw)
