"""Guide authoring: keyframed edits layered on a guide animation, and keyframed guide poses.

The tracking solver takes "a coarse animation of guide hairs as input" (paper 3); paper 4 makes
it in two ways, both supported here on top of the sources of ``guides.py``:

* **Edits** (``guides.edits``, ``apply_edits``): "an initial simulation on a coarse set of guide
  hairs using best-guess parameters" (``guides.source=simulated``), then the artist "edits the
  motion of one guide hair as desired using conventional keyframing" (4, Goaling and Celia).
  Each edit acts on one guide, in the order listed, on the world positions the source (and the
  edits before it) produced, at every frame:

  - ``rotate``: rotation about the guide's root by ``weight(t) * angle_deg`` about ``axis``
    (body frame of the scene's rigid motion, so the edit rides with the head).  Edge lengths
    are kept exactly and the root vertex does not move.  The second vertex turns with the rest
    of the guide: unlike the detail hair (whose first two vertices are carried by the body), a
    guide needs only its root on the body: the tracker transports the body frame onto the
    guide's first edge, whatever its direction (``constraints.TrackingConstraints._frames``);
  - ``displace``: the vertex at normalised rest arc length s (0 at the root, 1 at the tip;
    measured on frame 0 of the animation the edits start from) moves by
    ``weight(t) * s**falloff * offset`` (``offset`` in the body frame, metres at the tip).
    ``falloff`` > 0 keeps the root fixed.  A displacement changes edge lengths; the tracker
    copes with stretched or shortened guides through sliding targets (paper 3.2, Fig. 2), with
    static targets the detail hair is pulled along with the stretch.

  ``weight(t)`` is keyed by ``times``/``weights`` (``KeyedWeight``): a C1 piecewise cubic that
  eases in and out of its first and last key and is held outside them.  It is a multiplier, not
  a blend factor: weights may be negative or exceed 1, so one rotate edit with keys
  ``weights: [0, 1, -2, 3]`` swings a guide to and fro with growing amplitude (the stylised guide
  of Fig. 7 with ``guides.source=rigid``).

* **Keyframed guides** (``guides.source=keyframed``, ``keyframed_positions``): "a keyframe
  animation of a single guide hair" without simulation as input (4, Stylization).  Each key gives
  all guides' vertices in the body frame; poses are interpolated by clamped cubic splines in time
  (C2, zero velocity at the first and last key, held outside, as ``scene.motion`` with ``cubic``)
  relative to the guide roots, which must be the same in every key: guides are rooted on the body.
  Spline interpolation of positions does not keep edge lengths between keys (a swing keyed at its
  extremes cuts the chord): rotate edits are the better tool for swinging.

The authored animation (source + edits) is what a run saves as ``guides.npz``; it can be tracked
again with ``guides.source=file`` (and no edits, or they would be applied twice).

Authored guides may not turn their first edge by ``MAX_ROOT_TURN_DEG`` or more away from its rest
direction in the body frame: the tracker's root frame is the body frame turned by the smallest
rotation onto the first edge (paper 3.2), which is undefined at 180 degrees and jumps across it.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial.transform import Rotation

from hairexp.errors import MAX_COORDINATE, InputError, choice_name
from hairexp.guides.store import FrameStore
from hairexp.model.rigid import MAX_KEY_DEGREES, cubic_spline, motion_poses
from hairexp.model.strands import validate_polylines

#: Largest turn (degrees) of a guide's first edge away from its rest direction, in the body frame.
MAX_ROOT_TURN_DEG = 175.0
#: Largest distance (m) between a guide's root in keyframe 0 and in another keyframe.
ROOT_TOLERANCE = 1e-9


def _kind(value) -> str:
    return choice_name(value)


def _vector(value, where: str, nonzero: bool = False) -> np.ndarray:
    """A finite 3-vector from a config list (an InputError naming ``where`` otherwise)."""
    try:
        v = np.asarray(list(value), dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"must be a list of 3 numbers: {exc}", where) from exc
    if v.shape != (3,):
        raise InputError(f"must have 3 components, got {v.size}", where)
    if not np.isfinite(v).all():
        raise InputError(f"must be finite, got {v.tolist()}", where)
    if nonzero and np.linalg.norm(v) == 0:
        raise InputError("must not be the zero vector", where)
    return v


def _increasing_times(times, where: str) -> np.ndarray:
    t = np.asarray(list(times), dtype=np.float64).reshape(-1)
    if t.size == 0:
        raise InputError("needs at least one keyframe", where)
    if not np.isfinite(t).all():
        raise InputError(f"must be finite, got {t.tolist()}", where)
    if np.any(np.diff(t) <= 0):
        raise InputError(f"keyframe times must increase strictly, got {t.tolist()}", where)
    return t


#: a keyed edit weight at most this in magnitude (1 is the whole edit)
MAX_EDIT_WEIGHT = 1e3


class KeyedWeight:
    """A scalar keyed in time: w(t_k) = w_k, C1, held constant outside [t_0, t_last].

    Piecewise cubic Hermite with the PCHIP slopes of Fritsch and Carlson at interior keys (the
    weighted harmonic mean of the neighbouring secants, zero where the keys have a local extremum
    or a plateau) and zero slope at the first and last key, so the curve eases into the held
    values outside the keys (C1 there too).  No overshoot: between two keys w stays within their
    values.  One key: a constant.  ``where`` is the config node (errors name ``where.times`` or
    ``where.weights``).
    """

    def __init__(self, times, weights, where: str):
        self.times = _increasing_times(times, f"{where}.times")
        w = np.asarray(list(weights), dtype=np.float64).reshape(-1)
        if w.size != self.times.size:
            raise InputError(f"has {w.size} values but {where}.times has {self.times.size}: one weight per time",
                             f"{where}.weights")
        if not np.isfinite(w).all():
            raise InputError(f"must be finite, got {w.tolist()}", f"{where}.weights")
        if np.abs(w).max() > MAX_EDIT_WEIGHT:   # 1e300 made the guide NaN (probe of issue 12, round 14)
            raise InputError(f"must be within +-{MAX_EDIT_WEIGHT:g} (1: the whole edit), got {w.tolist()}", f"{where}.weights")
        self.weights = w
        self._curve = None
        if w.size > 1:
            from scipy.interpolate import CubicHermiteSpline   # imported when used (see rigid.cubic_spline)

            self._curve = CubicHermiteSpline(self.times, w, self.slopes(self.times, w))

    @staticmethod
    def slopes(t: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Key slopes: Fritsch-Carlson at interior keys, 0 at the ends."""
        h = np.diff(t)
        d = np.diff(w) / h
        m = np.zeros_like(w)
        for k in range(1, len(w) - 1):
            if d[k - 1] * d[k] > 0:
                w1, w2 = 2 * h[k] + h[k - 1], h[k] + 2 * h[k - 1]
                m[k] = (w1 + w2) / (w1 / d[k - 1] + w2 / d[k])
        return m

    def __call__(self, t):
        t = np.asarray(t, dtype=np.float64)
        if self._curve is None:
            return np.full(t.shape, self.weights[0])
        # held values exactly (a weight keyed back to 0 leaves the later frames untouched)
        return np.where(t <= self.times[0], self.weights[0], np.where(t >= self.times[-1], self.weights[-1],
                        self._curve(np.clip(t, self.times[0], self.times[-1]))))


def rest_arclength_fraction(P: np.ndarray) -> np.ndarray:
    """(n,) normalised arc length of the vertices of polyline P: 0 at the root, 1 at the tip."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P, axis=0), axis=1))])
    return s / s[-1]


#: frames edited (or keyframed) together: the memory of a block, whatever the animation's length
BLOCK_FRAMES = 256


#: the largest rotate edit angle (degrees at weight 1): a keyframed rotation's bound (100 turns)
MAX_EDIT_DEGREES = MAX_KEY_DEGREES


#: the schema's defaults of the keys one kind of edit reads and the other does not (GuideEditConfig)
DEFAULT_AXIS = (0.0, 0.0, 1.0)
DEFAULT_FALLOFF = 1.0


def _differs(value, default) -> bool:
    """Whether a config value differs from ``default`` (a value that is not a number does: the
    kind's own check would refuse it)."""
    try:
        return not np.array_equal(np.asarray(value, dtype=float), np.asarray(default, dtype=float))
    except (TypeError, ValueError):
        return True


def _edit(i: int, e, G: int, offsets: np.ndarray, rest: np.ndarray):
    """Edit ``i`` checked, as a function ``op(P, times, R)`` that edits the frames P (n, Vg, 3) at
    ``times`` (n,) under body rotations R (n, 3, 3) in place."""
    where = f"guides.edits[{i}]"
    if getattr(e, "guide", None) is None:   # it defaulted to 0: an edit meant for all went to the first (probe of issue 12)
        raise InputError(f"missing: the index of the edited guide (0..{G - 1}), e.g. guide: 0", f"{where}.guide")
    g = int(e.guide)
    if not 0 <= g < G:
        raise InputError(f"guide index {g} out of range: the animation has {G} guide(s) (0..{G - 1})",
                         f"{where}.guide")
    weight = KeyedWeight(e.times, e.weights, where)
    a, b = int(offsets[g]), int(offsets[g + 1])
    kind = _kind(e.kind)
    # the other kind's amount set: that edit is not the one asked for (a rotate with an offset and no
    # angle did nothing, exit 0; probe of issue 12)
    if kind == "rotate" and np.any(np.asarray(e.offset, dtype=float) != 0):
        raise InputError("is a displace edit's key; a rotate edit turns the guide by angle_deg about axis "
                         "(kind: displace to move it by offset)", f"{where}.offset")
    if kind == "displace" and float(e.angle_deg) != 0:
        raise InputError("is a rotate edit's key; a displace edit moves the guide by offset "
                         "(kind: rotate to turn it by angle_deg)", f"{where}.angle_deg")
    # the same for the other kind's shape keys, set away from their defaults (an axis on a displace, a
    # falloff on a rotate were accepted and unused; probe of issue 12, round 19)
    if kind == "displace" and _differs(e.axis, DEFAULT_AXIS):
        raise InputError("is a rotate edit's key (the axis it turns about); a displace edit moves the guide by "
                         "offset, in the body frame (kind: rotate to turn it about axis)", f"{where}.axis")
    if kind == "rotate" and _differs(e.falloff, DEFAULT_FALLOFF):
        raise InputError("is a displace edit's key (the profile s^falloff of its offset); a rotate edit turns the "
                         "guide rigidly about its root (kind: displace to move it by offset x s^falloff)",
                         f"{where}.falloff")
    if kind == "rotate":
        axis = _vector(e.axis, f"{where}.axis", nonzero=True)
        axis /= np.linalg.norm(axis)
        angle = float(e.angle_deg)
        if not (np.isfinite(angle) and abs(angle) <= MAX_EDIT_DEGREES):
            # 1e308 reached the guides as "vertex is not finite", naming no key (probe of issue 12)
            raise InputError(f"must be a finite number of degrees within +-{MAX_EDIT_DEGREES:g} (100 turns), got {angle}",
                             f"{where}.angle_deg")
        if angle == 0:
            logging.getLogger("hairexp").warning("%s: angle_deg is 0: this rotate edit leaves the guide as it is", where)

        def rotate(P, times, R):
            w = weight(times)
            for f in np.flatnonzero(w != 0):
                Q = Rotation.from_rotvec(np.radians(w[f] * angle) * (R[f] @ axis)).as_matrix()
                x0 = P[f, a]
                P[f, a + 1:b] = x0 + (P[f, a + 1:b] - x0) @ Q.T
        return rotate
    if kind == "displace":
        offset = _vector(e.offset, f"{where}.offset")
        if float(np.abs(offset).max()) > MAX_COORDINATE:   # 1e300 overflowed into numpy warnings (probe, round 14)
            raise InputError(f"is {offset.tolist()}, more than {MAX_COORDINATE:g} m: hairexp reads metres", f"{where}.offset")
        p = float(e.falloff)
        if not (np.isfinite(p) and p > 0):
            raise InputError(f"must be a finite number > 0 (0 would move the root), got {p}", f"{where}.falloff")
        profile = rest_arclength_fraction(rest[a:b]) ** p       # 0 at the root exactly

        def displace(P, times, R):
            w = weight(times)
            for f in np.flatnonzero(w != 0):
                P[f, a:b] += w[f] * profile[:, None] * (R[f] @ offset)
        return displace
    raise InputError(f"unknown edit kind {kind!r} (rotate|displace)", f"{where}.kind")


def check_edits(edits, count: int | None) -> None:
    """Every edit of ``guides.edits`` checked as ``apply_edits`` checks it, before any run (a
    guide index out of range was found only when the variant that tracks the guides started,
    after the free variant had run; probe of issue 12, round 10).  ``count``: the number of
    guides when the config fixes it; None (a file or a stage) checks all but the index's upper
    bound, which ``apply_edits`` checks once the guides are read."""
    if not edits:
        return
    given = [int(e.guide) for e in edits if getattr(e, "guide", None) is not None]
    G = int(count) if count is not None else max(given + [0]) + 1
    offsets = np.arange(G + 1) * 3
    rest = np.zeros((3 * G, 3))
    rest[:, 1] = -np.tile([0.0, 0.5, 1.0], G)   # straight 3-vertex stand-ins: only the keys are checked here
    log = logging.getLogger("hairexp")
    quiet, log.disabled = log.disabled, True   # its warnings are said once, when the edits apply
    try:
        for i, e in enumerate(edits):
            _edit(i, e, G, offsets, rest)
    finally:
        log.disabled = quiet


def apply_edits(positions, offsets: np.ndarray, fps: float, motion, edits):
    """Apply ``guides.edits`` (a list of GuideEditConfig) in order to world guide positions
    (F, Vg, 3) whose frame f is at time f / fps; returns new positions (the input is kept):
    an array for an array, a ``FrameStore`` for a ``FrameStore`` (edited BLOCK_FRAMES frames at
    a time: the memory of a block).  ``motion`` (RigidMotion) gives the body frame the axes and
    offsets are expressed in."""
    offsets = np.asarray(offsets, dtype=np.int64)
    G = len(offsets) - 1
    rest = np.array(positions[0], dtype=np.float64)
    ops = [_edit(i, e, G, offsets, rest) for i, e in enumerate(edits)]
    n = len(positions)
    stored = isinstance(positions, FrameStore)
    out = FrameStore(rest.shape) if stored else np.empty((n, *rest.shape))
    turn = RootTurn(offsets, "guides.edits")
    for start in range(0, n, BLOCK_FRAMES):
        P = np.array(positions[start:start + BLOCK_FRAMES], dtype=np.float64)
        times = np.arange(start, start + len(P)) / fps
        R = motion_poses(motion, times)[0]          # (n, 3, 3) body -> world
        for op in ops:
            op(P, times, R)
        turn.add(P, R, start)
        if stored:
            for X in P:
                out.append(X)
        else:
            out[start:start + len(P)] = P
    turn.check()
    return out


class RootTurn:
    """Every guide's first edge stays within MAX_ROOT_TURN_DEG of its frame-0 direction, both
    seen in the body frame; frames are added in blocks (``add``), ``check`` raises."""

    def __init__(self, offsets: np.ndarray, where: str):
        self.roots = np.asarray(offsets[:-1], dtype=np.int64)
        self.where = where
        self.e0 = self.n0 = None
        self.worst = (-1.0, 0, 0)   # (turn, frame, guide)

    def add(self, P: np.ndarray, R: np.ndarray, start: int) -> None:
        """Frames start.. of P (n, Vg, 3) with body rotations R (n, 3, 3)."""
        roots = self.roots
        e = np.einsum("fji,fgj->fgi", R, P[:, roots + 1] - P[:, roots])   # R^T (x1 - x0): body frame
        n = np.linalg.norm(e, axis=-1, keepdims=True)
        e = np.divide(e, n, out=np.zeros_like(e), where=n > 0)   # zero-length edges: left to validate_polylines
        if self.e0 is None:
            self.e0, self.n0 = e[:1].copy(), n[:1].copy()
        turn = np.degrees(np.arccos(np.clip(np.sum(e * self.e0, axis=-1), -1.0, 1.0)))   # (n, G)
        turn[(n[..., 0] == 0) | (self.n0[:, :, 0] == 0)] = 0.0
        f, g = np.unravel_index(int(np.argmax(turn)), turn.shape)
        if turn[f, g] > self.worst[0]:
            self.worst = (float(turn[f, g]), start + int(f), int(g))

    def check(self) -> None:
        turn, f, g = self.worst
        if turn >= MAX_ROOT_TURN_DEG:
            raise InputError(f"guide {g}'s first edge turns {turn:.1f} deg from its rest direction (frame {f}); "
                             f"the tracker's root frame is undefined at 180 deg: keep it below {MAX_ROOT_TURN_DEG:g} "
                             "deg", self.where)


def keyframed_positions(gcfg, motion, frames: int, fps: float) -> tuple[FrameStore, np.ndarray]:
    """World guide positions (frames + 1, count * n_vertices, 3; a ``FrameStore``) and offsets from
    ``guides.keyframes`` (source=keyframed; see the module doc)."""
    keys = list(gcfg.keyframes)
    if not keys:
        raise InputError("source=keyframed needs at least one keyframe", "guides.keyframes")
    count, nv = int(gcfg.count), int(gcfg.n_vertices)
    if count < 1:
        raise InputError(f"must be >= 1, got {count}", "guides.count")
    if nv < 2:
        raise InputError(f"must be >= 2, got {nv}", "guides.n_vertices")
    key_times = np.array([float(k.time) for k in keys])
    for i, t in enumerate(key_times):
        if not np.isfinite(t):
            raise InputError(f"must be finite, got {t}", f"guides.keyframes[{i}].time")
        if i and t <= key_times[i - 1]:
            raise InputError(f"keyframe times must increase strictly: {t} after {key_times[i - 1]}",
                             f"guides.keyframes[{i}].time")
    offsets = np.arange(count + 1) * nv
    roots = offsets[:-1]
    poses = []
    for i, k in enumerate(keys):
        where = f"guides.keyframes[{i}].points"
        pts = [list(p) for p in k.points]
        if len(pts) != count * nv:
            raise InputError(f"has {len(pts)} points, expected guides.count x guides.n_vertices = {count} x {nv} = "
                             f"{count * nv} (every keyframe holds the same guides, guide by guide)", where)
        for j, p in enumerate(pts):
            if len(p) != 3:
                raise InputError(f"point {j} has {len(p)} coordinates, expected 3", where)
        X, _ = validate_polylines(np.asarray(pts, dtype=np.float64), np.full(count, nv), where, min_vertices=2)
        if poses:
            moved = np.linalg.norm(X[roots] - poses[0][roots], axis=1)
            if moved.max() > ROOT_TOLERANCE:
                g = int(np.argmax(moved))
                raise InputError(f"guide {g}'s root (its vertex 0) is {moved[g]:.3g} m from where keyframe 0 puts it: "
                                 "guide roots are fixed on the body, only the other vertices can be keyed", where)
        poses.append(X)
    K = np.stack(poses)                                        # (keys, Vg, 3) body frame
    root = np.repeat(K[0, roots], nv, axis=0)                  # (Vg, 3), exactly the same in every frame
    rel = K - root
    rel[:, roots] = 0.0                                        # the spline keeps the roots exactly
    spline = None if len(keys) == 1 else cubic_spline()(key_times, rel, axis=0, bc_type="clamped")
    world = FrameStore(root.shape)
    turn = RootTurn(offsets, "guides.keyframes")
    for start in range(0, frames + 1, BLOCK_FRAMES):          # a block of frames at a time
        t_out = np.arange(start, min(start + BLOCK_FRAMES, frames + 1)) / fps
        if spline is None:
            B = np.repeat(rel, len(t_out), axis=0)
        else:
            B = spline(np.clip(t_out, key_times[0], key_times[-1]))
        B = B + root
        W = np.stack([motion.transform(B[f], t) for f, t in enumerate(t_out)])
        turn.add(W, np.stack([motion.pose(t)[0] for t in t_out]), start)
        for X in W:
            world.append(X)
    turn.check()
    return world, offsets
