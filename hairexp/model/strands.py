"""Packed piecewise-linear strands: rest shape, lumped masses and element stencils.

Vertices of all strands are stored in one ``(V, 3)`` array, strand ``s`` owning rows
``offsets[s]:offsets[s+1]``.  The first two vertices of every strand are kinematic (carried
by the rigid body, paper 3.4 "attachment point"); the rest are degrees of freedom, ordered
strand by strand and vertex by vertex so that the Hessian is banded per strand.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hairexp.errors import MAX_COORDINATE, InputError, check_extent, real, real_array, whole_array

#: Vertices per strand held kinematically by the root rigid body.
N_ROOT_VERTICES = 2
#: An edge shorter than this (m) is treated as zero-length input.
MIN_EDGE_LENGTH = 1e-9
#: m, the longest strand ``Strands.from_polylines`` builds (hair is metres long at most; the
#: procedural builders' scene.length has the same bound): a 22 km strand of a stage in millimetres
#: read as metres was built, and a curve at 1e300 m made an infinite length (probe of issue 16)
MAX_STRAND_LENGTH = 100.0


#: the largest turn between two consecutive edges of a curve that ``validate_polylines`` accepts (degrees)
MAX_TURN_DEG = 175.0


def within_curves(offsets: np.ndarray, n_steps: int) -> np.ndarray:
    """(n_steps,) bool: which steps between consecutive packed points (curve offsets ``offsets``)
    are edges of a curve, not the step from one curve's last vertex to the next curve's first."""
    within = np.ones(n_steps, dtype=bool)
    within[offsets[1:-1] - 1] = False
    return within


def curve_vertex(offsets: np.ndarray, v: int) -> tuple[int, int]:
    """(curve, index along it) of the packed vertex ``v`` of curves with vertex ``offsets``."""
    c = int(np.searchsorted(offsets, v, side="right") - 1)
    return c, int(v) - int(offsets[c])


def first_short_edge(points: np.ndarray, offsets: np.ndarray) -> int | None:
    """The first edge within a curve shorter than MIN_EDGE_LENGTH, as the packed index of its
    first vertex, or None (squared lengths: points near 1e300 give inf, not a short edge)."""
    d = np.diff(points, axis=0)
    with np.errstate(over="ignore", invalid="ignore"):
        sq = np.einsum("ij,ij->i", d, d)
    short = within_curves(offsets, len(sq)) & (sq < MIN_EDGE_LENGTH ** 2)
    return int(np.flatnonzero(short)[0]) if short.any() else None


def validate_polylines(points: np.ndarray, counts: np.ndarray, where: str, min_vertices: int = 2,
                       folds: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Check packed polylines and return them as float64 ``(V,3)`` and int64 counts.

    Raises InputError naming ``where`` and the offending curve index for NaN/inf,
    wrong shapes, counts that do not add up, too few vertices, or zero-length edges, and (with
    ``folds``) for folds (``check_folds``).
    """
    points = real_array(points, f"{where} points")
    counts = whole_array(counts, f"{where} vertex counts")
    if counts.ndim != 1:   # a (1, 1) array was flattened without a word (probe of issue 12, round 15)
        raise InputError(f"vertex counts must be a 1-D sequence (one count a curve), got shape {counts.shape}", where)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"points must have shape (V, 3), got {points.shape}", where)
    if counts.size == 0:
        raise InputError("no curves given", where)
    # a curve's own count first: a negative one was named only as a sum that did not add up (probe, round 19)
    for s in np.flatnonzero(counts < min_vertices):
        raise InputError(f"curve {s} has {counts[s]} {'vertex' if counts[s] == 1 else 'vertices'}, needs at least "
                         f"{min_vertices}", where)
    if counts.sum() != points.shape[0]:
        raise InputError(f"vertex counts add up to {int(counts.sum())} but there are {points.shape[0]} points", where)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        v = int(np.flatnonzero(bad)[0])
        c, k = curve_vertex(offsets, v)
        raise InputError(f"curve {c} vertex {k} is not finite: {points[v].tolist()}", where)
    e = first_short_edge(points, offsets)   # points near 1e300: inf lengths, which the extent check names
    if e is not None:
        c, k = curve_vertex(offsets, e)
        raise InputError(f"curve {c} has a zero-length edge between vertices {k} and {k + 1}", where)
    if folds:
        check_folds(points, counts, where)
    return points, counts


def suspect_frames(frames: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(F,) bool: the frames of ``frames`` (F, V, 3; packed polylines of ``counts``, already
    checked once by ``validate_polylines``) that ``validate_polylines``, ``check_folds`` or
    ``errors.check_extent`` could refuse, found for all frames at once: a point not finite or
    near MAX_COORDINATE, an edge near MIN_EDGE_LENGTH or a turn near MAX_TURN_DEG (each with a
    margin, so that round-off cannot hide a frame).  Only the frames it names need those checks
    (a guide animation of 20,000 frames took 11 s checked frame by frame)."""
    P = np.asarray(frames, dtype=np.float64)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    with np.errstate(invalid="ignore", over="ignore"):
        bad = ~np.isfinite(P).all(axis=(1, 2)) | (np.abs(P) > 0.999 * MAX_COORDINATE).any(axis=(1, 2))
        d = np.diff(P, axis=1)
        seg = np.sqrt((d * d).sum(-1))                       # (F, V - 1)
        within = within_curves(offsets, seg.shape[1])
        bad |= (within & ~(seg > 2.0 * MIN_EDGE_LENGTH)).any(axis=1)
        u = d / np.maximum(seg, 1e-300)[..., None]
        cos = (u[:, :-1] * u[:, 1:]).sum(-1)                 # (F, V - 2)
        bad |= ((within[:-1] & within[1:]) & ~(cos > np.cos(np.radians(MAX_TURN_DEG)) + 1e-6)).any(axis=1)
    return bad


def check_folds(points: np.ndarray, counts: np.ndarray, where: str) -> None:
    """InputError naming the curve and vertex where two consecutive edges of a curve turn by more
    than MAX_TURN_DEG: the bending energy's curvature 2 tan(turn / 2) and the guides' parallel
    transport are singular at 180 degrees (a curve folded back on itself diverged the first step,
    told as "try a smaller solver.dt"; probe of issue 12).  ``points`` finite, no zero-length edge."""
    offsets = np.concatenate([[0], np.cumsum(counts)])
    with np.errstate(over="ignore", invalid="ignore"):   # points near 1e300: inf lengths, which the extent check names
        seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
    within = within_curves(offsets, len(seg))
    d = np.diff(points, axis=0) / np.maximum(seg, 1e-300)[:, None]
    cos = (d[:-1] * d[1:]).sum(1)
    fold = within[:-1] & within[1:] & (cos < np.cos(np.radians(MAX_TURN_DEG)))
    if fold.any():
        e = int(np.flatnonzero(fold)[0])
        c, k = curve_vertex(offsets, e)
        turn = float(np.degrees(np.arccos(np.clip(cos[e], -1.0, 1.0))))
        raise InputError(f"curve {c} folds back on itself at vertex {k + 1} (its edges turn by {turn:.1f} "
                         f"degrees there, more than {MAX_TURN_DEG:g})", where)


@dataclass(frozen=True)
class Strands:
    """Static description of the detail hair (never changes during a run).

    Attributes (V vertices, E edges, B bending elements, S strands, N free DOFs = 3 * free vertices):
        rest:        (V, 3) rest positions in world space at t = 0 (m)
        offsets:     (S + 1,) vertex offsets of each strand
        masses:      (V,) lumped masses (kg) from the linear density
        edges:       (E, 2) vertex indices of each edge
        rest_lengths:(E,) rest edge lengths (m)
        bends:       (B, 3) vertex indices (i-1, i, i+1) of each interior vertex
        kinematic:   (V,) True for root vertices carried by the rigid body
        free_slot:  (V,) index of each vertex among the free vertices, -1 for kinematic ones
    """

    rest: np.ndarray
    offsets: np.ndarray
    masses: np.ndarray
    edges: np.ndarray
    rest_lengths: np.ndarray
    bends: np.ndarray
    kinematic: np.ndarray
    free_slot: np.ndarray

    @property
    def n_vertices(self) -> int:
        return self.rest.shape[0]

    @property
    def n_strands(self) -> int:
        return len(self.offsets) - 1

    @property
    def n_free(self) -> int:
        return int((~self.kinematic).sum())

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.offsets)

    @property
    def strand_of_vertex(self) -> np.ndarray:
        return np.repeat(np.arange(self.n_strands), self.counts)

    @property
    def inverse_masses(self) -> np.ndarray:
        """(V,) 1 / m, 0 for the kinematic (root) vertices, which impulses cannot move."""
        return np.where(self.kinematic, 0.0, 1.0 / self.masses)

    def strand_lengths(self) -> np.ndarray:
        """(S,) rest length of each strand (m)."""
        per_edge_strand = self.strand_of_vertex[self.edges[:, 0]]
        return np.bincount(per_edge_strand, weights=self.rest_lengths, minlength=self.n_strands)

    @staticmethod
    def from_polylines(points: np.ndarray, counts: np.ndarray, linear_density: float, where: str = "strands") -> "Strands":
        """Build strands from packed rest polylines.  ``linear_density`` in kg/m."""
        points, counts = validate_polylines(points, counts, where, min_vertices=N_ROOT_VERTICES + 1)
        check_extent(points, where, counts)   # a point 1e300 away: a unit error, not an infinite length
        real(linear_density, f"{where} linear density (kg/m)", lo=0.0, lo_open=True)
        offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        V = points.shape[0]
        first = offsets[:-1]
        last = offsets[1:] - 1
        is_last = np.zeros(V, dtype=bool)
        is_last[last] = True
        is_first = np.zeros(V, dtype=bool)
        is_first[first] = True
        starts = np.flatnonzero(~is_last)
        edges = np.stack([starts, starts + 1], axis=1)
        rest_lengths = np.linalg.norm(points[edges[:, 1]] - points[edges[:, 0]], axis=1)
        mids = np.flatnonzero(~is_first & ~is_last)
        bends = np.stack([mids - 1, mids, mids + 1], axis=1)
        masses = np.zeros(V)
        half = 0.5 * linear_density * rest_lengths
        np.add.at(masses, edges[:, 0], half)
        np.add.at(masses, edges[:, 1], half)
        local = np.arange(V) - np.repeat(first, counts)
        kinematic = local < N_ROOT_VERTICES
        free_slot = np.full(V, -1, dtype=np.int64)
        free_slot[~kinematic] = np.arange(int((~kinematic).sum()))
        for a in (points, offsets, masses, edges, rest_lengths, bends, kinematic, free_slot):
            a.setflags(write=False)
        strands = Strands(points, offsets, masses, edges, rest_lengths, bends, kinematic, free_slot)
        lengths = strands.strand_lengths()
        long = np.flatnonzero(lengths > MAX_STRAND_LENGTH)
        if len(long):
            c = int(long[0])
            raise InputError(f"curve {c} is {lengths[c]:.6g} m long, more than {MAX_STRAND_LENGTH:g} m: hair is metres long "
                             "at most; hairexp reads metres (check the units of the input)", where)
        return strands
