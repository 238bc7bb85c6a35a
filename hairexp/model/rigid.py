"""Keyframed rigid motion: translation plus rotation, interpolated smoothly, with velocities.

A pose maps body coordinates X to world coordinates ``x = R(t) X + T(t)``.  Keyframes hold
translations (m) and rotations (rotation vectors, radians).  Interpolation:

* ``cubic``:  C2 cubic splines of the translation and of the rotation vector, both with zero
  velocity at the first and last keyframe ("clamped"), so the body starts and stops smoothly;
  R(t) = exp(r(t)) and omega = J_l(r) dr/dt (J_l the left Jacobian of SO(3)).  Rotation
  vectors are interpolated as given: key them without jumps of 2 pi;
* ``linear``: piecewise-linear translation and slerp: constant velocity per segment, so a
  keyframe can stop the body *suddenly* (the goaling scene's "stops suddenly").

Outside the keyed range the first/last pose is held with zero velocity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from hairexp.errors import MAX_COORDINATE, MAX_SPEED, InputError, real_array


def left_jacobian(r: np.ndarray) -> np.ndarray:
    """J_l(r) of SO(3): the world angular velocity of exp(r(t)) is J_l(r) dr/dt."""
    th = float(np.linalg.norm(r))
    K = np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])
    if th < 1e-6:
        return np.eye(3) + 0.5 * K + K @ K / 6.0
    return np.eye(3) + (1 - np.cos(th)) / th ** 2 * K + (th - np.sin(th)) / th ** 3 * K @ K


def exp_so3(r: np.ndarray) -> np.ndarray:
    """The rotation matrix of rotation vector r (Rodrigues: I + sin(th)/th K + (1 - cos th)/th^2 K^2,
    with (1 - cos th) = 2 sin^2(th / 2), and its series below th = 1e-6)."""
    x, y, z = float(r[0]), float(r[1]), float(r[2])
    th = math.sqrt(x * x + y * y + z * z)
    if th < 1e-6:
        a, b = 1.0 - th * th / 6.0, 0.5 - th * th / 24.0
    else:
        s = math.sin(0.5 * th)
        a, b = math.sin(th) / th, 2.0 * s * s / (th * th)
    K = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + a * K + b * (K @ K)


def exp_so3_batch(r: np.ndarray) -> np.ndarray:
    """``exp_so3`` of each row of r (n, 3): (n, 3, 3)."""
    r = np.asarray(r, dtype=np.float64).reshape(-1, 3)
    x, y, z = r[:, 0], r[:, 1], r[:, 2]
    th = np.sqrt(x * x + y * y + z * z)
    small = th < 1e-6
    ths = np.where(small, 1.0, th)
    s = np.sin(0.5 * ths)
    a = np.where(small, 1.0 - th * th / 6.0, np.sin(ths) / ths)
    b = np.where(small, 0.5 - th * th / 24.0, 2.0 * s * s / (ths * ths))
    K = np.zeros((len(r), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 0], K[:, 1, 2], K[:, 2, 0], K[:, 2, 1] = -z, y, z, -x, -y, x
    return np.eye(3) + a[:, None, None] * K + b[:, None, None] * (K @ K)


#: s, relative: a keyframe this close to a step's start counts as at its start (``velocity_jumps``)
TIME_TOL = 1e-9
#: relative (to max(1, |v|) in m/s or rad/s): a velocity change at a key above this is a jump
VELOCITY_JUMP_TOL = 1e-9
#: a key counts as a velocity jump only if the segments on both sides span this many steps
MIN_SEGMENT_STEPS = 2.0

#: degrees, a keyframed rotation's angles at most this (also a guide edit's angle_deg bound, 100 turns)
MAX_KEY_DEGREES = 36000.0


def cubic_spline():
    """scipy's ``CubicSpline``, imported when first asked for: ``scipy.interpolate`` (with the
    ``scipy.optimize`` it imports) takes 0.3-0.4 s to import, which a run whose keys are all
    linear (Celia's) does not need."""
    from scipy.interpolate import CubicSpline

    return CubicSpline


@dataclass
class RigidMotion:
    times: np.ndarray          # (K,) s, strictly increasing
    translations: np.ndarray   # (K, 3) m
    rotvecs: np.ndarray        # (K, 3) rad
    interpolation: str = "cubic"
    where: str = "motion"      # the input the keyframes came from (errors name it)
    #: s: the keys whose velocity change is a jump (``velocity_jumps``), the others samples of a
    #: smooth motion (a USD transform read between its keyframes, hairexp/io/usd_layout.py
    #: ``read_motion``); None: any key whose segments span MIN_SEGMENT_STEPS steps
    jump_times: np.ndarray | None = None
    #: linear keys: two consecutive rotation vectors about one axis (or one of them zero) turn by
    #: their difference, whole turns included (a config's ``rotations_deg`` keys 0, 720, 1440 about
    #: y spin the body twice a segment; the shortest rotation between them is none: the paddle of an
    #: independent probe, 2026-12-07, never turned), as cubic keys do; other pairs, and all of them
    #: when False (rotations read from matrices, a USD stage's), the shortest rotation between them
    turns: bool = False

    def __post_init__(self) -> None:
        self.times = real_array(self.times, f"{self.where}.times")
        if self.times.ndim > 1:   # a (1, 1) array was flattened without a word (probe of issue 12, round 15)
            raise InputError(f"must be a 1-D sequence of keyframe times, got shape {self.times.shape}", f"{self.where}.times")
        self.times = self.times.reshape(-1)
        K = self.times.size
        for name in ("translations", "rotvecs"):
            a = real_array(getattr(self, name), f"{self.where}.{name}")
            if a.size != 3 * K:
                raise InputError(f"{name} must be {K} x 3 numbers (one per keyframe time), got shape {a.shape}",
                                 self.where)
        self.translations = np.asarray(self.translations, dtype=np.float64).reshape(K, 3) if K else np.zeros((0, 3))
        self.rotvecs = np.asarray(self.rotvecs, dtype=np.float64).reshape(K, 3) if K else np.zeros((0, 3))
        if K == 0:
            raise InputError("a rigid motion needs at least one keyframe", f"{self.where}.times")
        for name, a in (("times", self.times), ("translations", self.translations), ("rotations", self.rotvecs)):
            bad = np.argwhere(~np.isfinite(a))
            if bad.size:   # which list and which value (it said "keyframes contain NaN or inf"; probe of issue 12, round 37)
                k = int(bad[0][0])
                raise InputError(f"keyframe {k} is not finite: {a[k].tolist() if a.ndim > 1 else float(a[k])} (NaN or "
                                 "inf)", f"{self.where}.{name}")
        far = np.flatnonzero(np.abs(self.translations).max(axis=1) > MAX_COORDINATE)
        if far.size:   # a body 1e20 m away at one time code ran to the end with unconverged steps (probe, round 12)
            k = int(far[0])
            raise InputError(f"the translation at keyframe {k} (t = {self.times[k]:g} s) is {self.translations[k].tolist()}, "
                             f"more than {MAX_COORDINATE:g} m from the origin: hairexp reads metres (check the units "
                             "of the input)", f"{self.where}.translations")
        if K > 1 and np.all(np.diff(self.times) > 0):
            speed = np.linalg.norm(np.diff(self.translations, axis=0), axis=1) / np.diff(self.times)
            # at the limit to round-off (100 m in 0.1 s is 1000.0000000000002 m/s: refused as "1000 m/s, more
            # than 1000 m/s"; independent probe of issue 12, round 26)
            # a 100 m jump between two USD samples "completed" at 299,900 % stretch
            if speed.max() > MAX_SPEED * (1 + 1e-9):
                k = int(np.argmax(speed))
                raise InputError(f"moves {speed[k]:.4g} m/s between keyframes {k} and {k + 1} (t = {self.times[k]:g} "
                                 f"and {self.times[k + 1]:g} s), more than {MAX_SPEED:g} m/s: a jump, or a unit "
                                 "error (hairexp reads metres and seconds)", f"{self.where}.translations")
        if K > 1 and np.any(np.diff(self.times) <= 0):
            raise InputError(f"keyframe times must increase strictly, got {self.times.tolist()}", f"{self.where}.times")
        if self.interpolation not in ("cubic", "linear"):
            raise InputError(f"unknown interpolation {self.interpolation!r} (cubic|linear)", f"{self.where}.interpolation")
        turn = np.linalg.norm(self.rotvecs, axis=1) if K else np.zeros(0)
        if turn.size and turn.max() > np.radians(MAX_KEY_DEGREES):   # 1e6 rad was taken (probe of issue 12, round 14)
            k = int(np.argmax(turn))
            raise InputError(f"the rotation at keyframe {k} turns {turn[k]:.6g} rad, more than {MAX_KEY_DEGREES:g} degrees "
                             "(100 turns): a unit error (hairexp reads radians in rotation vectors)", f"{self.where}.rotvecs")
        rots = Rotation.from_rotvec(self.rotvecs)
        self._static = K == 1
        self._pos = self._rot = None
        if K > 1 and self.interpolation == "cubic":
            CubicSpline = cubic_spline()
            self._pos = CubicSpline(self.times, self.translations, bc_type="clamped")
            self._rot = CubicSpline(self.times, self.rotvecs, bc_type="clamped")
        elif K > 1:
            # scipy's Slerp without its per-call overhead (``_pose``; about 0.1 ms a call, a step
            # asks several times): R(t) = R_k exp(alpha log(R_k^T R_k+1)); ``velocity`` takes the
            # segments' rates from the same relative rotation vectors
            self._key_R = rots.as_matrix()
            self._key_rel = (rots[:-1].inv() * rots[1:]).as_rotvec()
            if self.turns:
                a, b = self.rotvecs[:-1], self.rotvecs[1:]
                cross = np.linalg.norm(np.cross(a, b), axis=1)
                coaxial = cross <= 1e-12 * np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-300)
                # about a common axis n, R_k^T R_k+1 = exp((theta_k+1 - theta_k) n) = exp(b - a)
                self._key_rel[coaxial] = (b - a)[coaxial]
        self._rots = rots
        self._cache: dict = {}
        # (K,) bool: the keys at ``jump_times`` (within TIME_TOL), found once (``velocity_jumps`` runs every step)
        self._jump_keys = None
        if self.jump_times is not None:
            jt = np.sort(np.asarray(self.jump_times, dtype=np.float64).reshape(-1))
            self._jump_keys = np.zeros(K, dtype=bool)
            if jt.size:
                j = np.searchsorted(jt, self.times)
                near = np.minimum(np.abs(jt[np.clip(j - 1, 0, jt.size - 1)] - self.times),
                                  np.abs(jt[np.clip(j, 0, jt.size - 1)] - self.times))
                self._jump_keys = near <= TIME_TOL * np.maximum(1.0, np.abs(self.times))

    @staticmethod
    def static() -> "RigidMotion":
        return RigidMotion(np.zeros(1), np.zeros((1, 3)), np.zeros((1, 3)))

    def velocity_jumps(self, t0: float, t1: float, since: float = -math.inf) -> bool:
        """Whether the velocity (translational or angular) jumps at a keyframe in [t0, t1) after
        ``since``: with linear interpolation, a key where the velocities of the segments before
        and after it differ (the first and last keys against the stillness outside the keys);
        cubic keys never jump (a spline with zero end velocities, held still outside).  Only keys
        whose segments on both sides span at least ``MIN_SEGMENT_STEPS`` x (t1 - t0) count (the
        stillness outside the keys is unbounded): keys as dense as the steps sample a motion (a USD
        stage's time samples at every frame), and restarting at each would make every step a
        restart.  With ``jump_times`` only the keys at those times count, whatever their spacing.
        Keys at or before ``since`` are left out: a run's initial state (t = 0) already
        moves with the velocity after a key there.  A time integrator restarts at a jump
        (hairexp/physics/integrators.py, "Driver discontinuities")."""
        if self._static or self.interpolation != "linear":
            return False
        ts = self.times
        tol = TIME_TOL * max(1.0, abs(float(t0)), abs(float(t1)))
        span = MIN_SEGMENT_STEPS * (float(t1) - float(t0)) - tol
        keyed = self._jump_keys
        for k in np.flatnonzero((ts >= t0 - tol) & (ts < t1 - tol) & (ts > since + tol)):
            if keyed is not None:
                if not keyed[k]:
                    continue
            elif (k > 0 and ts[k] - ts[k - 1] < span) or (k < len(ts) - 1 and ts[k + 1] - ts[k] < span):
                continue
            before = self._segment_velocity(k - 1)
            after = self._segment_velocity(k)
            scale = max(1.0, float(np.abs(before).max()), float(np.abs(after).max()))
            if float(np.abs(after - before).max()) > VELOCITY_JUMP_TOL * scale:
                return True
        return False

    def _segment_velocity(self, k: int) -> np.ndarray:
        """(6,) angular and translational velocity of linear segment k (keys k, k + 1); zero
        outside the keys."""
        if k < 0 or k >= len(self.times) - 1:
            return np.zeros(6)
        w, v = self.velocity(0.5 * (self.times[k] + self.times[k + 1]))
        return np.concatenate([w, v])

    def _clamp(self, t: float) -> tuple[float, bool]:
        lo, hi = self.times[0], self.times[-1]
        return float(min(max(t, lo), hi)), bool(t < lo or t > hi)

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Rotation matrix (3, 3) and translation (3,) at time t (the last few are cached:
        a step asks for the same few times many times)."""
        try:
            if isinstance(t, (str, bytes, bool)):   # float() took "0.1" (probe of issue 12, round 13)
                raise TypeError
            key = float(t)
        except (TypeError, ValueError):   # None: float()'s own TypeError (round 14)
            raise InputError(f"must be a real number of seconds, got {type(t).__name__} {t!r:.40}",
                             "RigidMotion.pose: t") from None
        hit = self._cache.get(key)
        if hit is None:
            if not math.isfinite(key):   # NaN gave NaN poses without a word
                raise InputError(f"must be a finite number of seconds, got {key}", "RigidMotion.pose: t")
            hit = self._pose(key)
            if len(self._cache) >= 16:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = hit
        return hit[0].copy(), hit[1].copy()

    def poses(self, times) -> tuple[np.ndarray, np.ndarray]:
        """Rotation matrices (n, 3, 3) and translations (n, 3) at each of ``times`` (n,): ``pose``'s
        values, computed for all times at once (a guide animation asks for one a frame: 20,000
        frames took 6 s one by one)."""
        t = real_array(times, "RigidMotion.poses: times").reshape(-1)
        if not np.isfinite(t).all():
            raise InputError(f"must be finite numbers of seconds, got {t[~np.isfinite(t)][:4].tolist()}",
                             "RigidMotion.poses: times")
        n = t.size
        if self._static:
            return (np.broadcast_to(self._rots[0].as_matrix(), (n, 3, 3)).copy(),
                    np.broadcast_to(self.translations[0], (n, 3)).copy())
        tc = np.clip(t, self.times[0], self.times[-1])
        if self._pos is not None:
            T = np.asarray(self._pos(tc), dtype=np.float64).reshape(n, 3)
        else:
            T = np.stack([np.interp(tc, self.times, self.translations[:, c]) for c in range(3)], axis=1)
        if self.interpolation == "cubic":
            R = Rotation.from_rotvec(np.asarray(self._rot(tc)).reshape(n, 3)).as_matrix().reshape(n, 3, 3)
        else:   # _pose's segment choice, for every time
            ts = self.times
            k = np.clip(np.searchsorted(ts, tc) - 1, 0, len(ts) - 2)
            k[tc == ts[0]] = 0
            alpha = (tc - ts[k]) / (ts[k + 1] - ts[k])
            R = self._key_R[k] @ exp_so3_batch(self._key_rel[k] * alpha[:, None])
        return R, T

    def _pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        if self._static:
            return self._rots[0].as_matrix(), self.translations[0].copy()
        tc, _ = self._clamp(t)
        if self._pos is not None:
            T = self._pos(tc)
        else:
            T = np.array([np.interp(tc, self.times, self.translations[:, c]) for c in range(3)])
        if self.interpolation == "cubic":
            R = Rotation.from_rotvec(self._rot(tc)).as_matrix()
        else:   # scipy's Slerp, its segment choice included (a key ends the segment before it)
            ts = self.times
            k = 0 if tc == ts[0] else min(max(int(np.searchsorted(ts, tc)) - 1, 0), len(ts) - 2)
            alpha = (tc - ts[k]) / (ts[k + 1] - ts[k])
            R = self._key_R[k] @ exp_so3(self._key_rel[k] * alpha)
        return R, np.asarray(T, dtype=np.float64)

    def velocity(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """World angular velocity omega (3,) rad/s and translational velocity (3,) m/s at t.

        For linear interpolation, at a keyframe the velocity of the *following* segment is
        returned (right-continuous)."""
        if self._static:
            return np.zeros(3), np.zeros(3)
        tc, outside = self._clamp(t)
        if outside or (self.interpolation == "linear" and t >= self.times[-1]):
            return np.zeros(3), np.zeros(3)
        R, _ = self.pose(tc)
        if self.interpolation == "cubic":
            Tdot = np.asarray(self._pos(tc, 1), dtype=np.float64)
            return left_jacobian(self._rot(tc)) @ self._rot(tc, 1), Tdot
        k = int(np.clip(np.searchsorted(self.times, tc, side="right") - 1, 0, len(self.times) - 2))
        dt = self.times[k + 1] - self.times[k]
        w = self._key_R[k] @ (self._key_rel[k] / dt)   # the segment's body-frame rate, in the world
        if self.interpolation == "linear":
            Tdot = (self.translations[k + 1] - self.translations[k]) / dt
        return w, Tdot

    def transform(self, X_body: np.ndarray, t: float) -> np.ndarray:
        R, T = self.pose(t)
        return X_body @ R.T + T

    def point_velocity(self, X_body: np.ndarray, t: float) -> np.ndarray:
        R, T = self.pose(t)
        w, Tdot = self.velocity(t)
        return np.cross(w, (X_body @ R.T)) + Tdot

    def to_body(self, x_world: np.ndarray, t: float) -> np.ndarray:
        R, T = self.pose(t)
        return (x_world - T) @ R


def motion_poses(motion, times: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R (n, 3, 3), T (n, 3)): ``motion``'s poses at ``times``, all at once where it can
    (``RigidMotion.poses``), else one by one."""
    if hasattr(motion, "poses"):
        return motion.poses(times)
    pairs = [motion.pose(float(t)) for t in times]
    return np.stack([p[0] for p in pairs]).reshape(-1, 3, 3), np.stack([p[1] for p in pairs]).reshape(-1, 3)
