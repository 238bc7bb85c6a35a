"""What a recording's default layout shows, decided from the run (pure numpy: no rerun here).

* ``Bounds``: the axis-aligned box of everything drawn over the whole run (hair, guides,
  colliders, the body), grown frame by frame, so the camera can be framed once for every
  frame without holding the frames.
* ``frame_camera``: an eye position and look target for a perspective camera of vertical field
  of view ``FOV_Y_DEG`` that keeps the whole box in view (every corner inside the frustum).
* ``grid_spacing``: a round spacing (1, 2 or 5 x 10^k m) for a floor grid at the scene's scale.
* ``choose_plots``: the plots that apply to a run (only metrics with data; a free run gets the
  energies, contacts and iterations; a tracked run adds the residual and the control effort).
* ``key_window``: the time window around the scene's key moment that the time panel loops.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from hairexp.errors import points_range

#: rerun's 3D view camera: vertical field of view (degrees) of its default perspective eye
FOV_Y_DEG = 55.0
#: extra room around the framed box (fraction of the distance that just fits it)
FRAME_MARGIN = 1.15
#: the eye looks from this far above the horizontal (degrees) and this far round from the view axis
ELEVATION_DEG = 15.0
AZIMUTH_DEG = 25.0
#: half-width (s) of the time window looped around the key moment
KEY_HALF_WINDOW = 0.3


@dataclass
class Bounds:
    """Axis-aligned bounds grown by ``add`` (non-finite points are ignored); empty until then."""
    lo: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))
    hi: np.ndarray = field(default_factory=lambda: np.full(3, -np.inf))

    def add(self, points) -> None:
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        lo, hi = points_range(p)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):   # a non-finite point: the others only
            p = p[np.isfinite(p).all(axis=1)]
            lo, hi = points_range(p)
        if len(p):
            self.lo = np.minimum(self.lo, lo)
            self.hi = np.maximum(self.hi, hi)

    def add_sphere(self, center, radius: float) -> None:
        """A ball of ``radius`` around ``center`` (a collider's bounding ball)."""
        c = np.asarray(center, dtype=np.float64)
        self.add(np.stack([c - radius, c + radius]))

    def union(self, other: "Bounds") -> "Bounds":
        return Bounds(np.minimum(self.lo, other.lo), np.maximum(self.hi, other.hi))

    @property
    def empty(self) -> bool:
        return not bool(np.all(self.hi >= self.lo))

    @property
    def center(self) -> np.ndarray:
        return 0.5 * (self.lo + self.hi)

    @property
    def size(self) -> np.ndarray:
        return self.hi - self.lo

    def corners(self) -> np.ndarray:
        """(8, 3) corners of the box."""
        return np.array([[x, y, z] for x in (self.lo[0], self.hi[0]) for y in (self.lo[1], self.hi[1])
                         for z in (self.lo[2], self.hi[2])])

    def to_json(self) -> dict:
        return {"min": self.lo.tolist(), "max": self.hi.tolist()}

    @classmethod
    def from_json(cls, d: dict) -> "Bounds":
        return cls(np.asarray(d["min"], dtype=np.float64), np.asarray(d["max"], dtype=np.float64))


def view_axis(size: np.ndarray, up: int = 1) -> np.ndarray:
    """The unit horizontal direction the camera looks along: the horizontal axis along which
    the box is thinnest (the motion is seen across its largest extents)."""
    horiz = [a for a in range(3) if a != up]
    a = min(horiz, key=lambda i: size[i])
    d = np.zeros(3)
    d[a] = 1.0
    return d


def frame_camera(b: Bounds, aspect: float = 1.0, up: int = 1, fov_y_deg: float = FOV_Y_DEG,
                 margin: float = FRAME_MARGIN) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(eye position, look target, eye up)`` of a camera that sees all of ``b``.

    The eye looks at the box's centre from the side (``view_axis``), turned ``AZIMUTH_DEG``
    about the up axis and raised ``ELEVATION_DEG``.  The distance is the smallest at which
    every corner lies inside the frustum of vertical field of view ``fov_y_deg`` and a view
    ``aspect`` (width / height) wide, times ``margin``: for a corner at ``(u, v, w)`` in the
    camera's right / up / toward-eye axes, ``d >= w + |v| / tan(fov_y / 2)`` and
    ``d >= w + |u| / (aspect tan(fov_y / 2))``.
    """
    if b.empty:
        raise ValueError("no bounds to frame: nothing was drawn")
    up_v = np.zeros(3)
    up_v[up] = 1.0
    toward = view_axis(b.size, up)
    az, el = np.radians(AZIMUTH_DEG), np.radians(ELEVATION_DEG)
    side = np.cross(up_v, toward)
    toward = np.cos(az) * toward + np.sin(az) * side
    toward = np.cos(el) * toward + np.sin(el) * up_v
    toward /= np.linalg.norm(toward)
    right = np.cross(up_v, toward)
    right /= np.linalg.norm(right)
    cam_up = np.cross(toward, right)
    c = b.center
    rel = b.corners() - c
    u, v, w = rel @ right, rel @ cam_up, rel @ toward
    t = np.tan(np.radians(fov_y_deg) / 2)
    span = max(float(np.max(b.size)), 1e-6)
    d = max(float(np.max(w + np.abs(v) / t)), float(np.max(w + np.abs(u) / (aspect * t))), 0.5 * span)
    return c + margin * d * toward, c, up_v


def in_view(points, eye, target, up, aspect: float = 1.0, fov_y_deg: float = FOV_Y_DEG) -> np.ndarray:
    """Whether each point lies inside the frustum of a camera at ``eye`` looking at ``target``."""
    fwd = np.asarray(target, float) - np.asarray(eye, float)
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, up)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, fwd)
    rel = np.asarray(points, float).reshape(-1, 3) - eye
    depth = rel @ fwd
    t = np.tan(np.radians(fov_y_deg) / 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        ok = (depth > 0) & (np.abs(rel @ cam_up) <= depth * t * (1 + 1e-9)) \
            & (np.abs(rel @ right) <= depth * t * aspect * (1 + 1e-9))
    return ok


def grid_spacing(b: Bounds, lines: float = 10.0) -> float:
    """A round spacing (1, 2 or 5 x 10^k m) giving about ``lines`` grid lines across the box's
    largest horizontal extent."""
    span = max(float(max(b.size[0], b.size[2])), 1e-3)
    raw = span / lines
    k = np.floor(np.log10(raw))
    for m in (1.0, 2.0, 5.0, 10.0):
        if m * 10 ** k >= raw:
            return float(m * 10 ** k)
    return float(10 ** (k + 1))   # pragma: no cover  (the loop ends at 10 x 10^k >= raw)


@dataclass(frozen=True)
class Plot:
    """One time-series plot: its title and the metric columns it draws (one series each)."""
    title: str
    columns: tuple[str, ...]


#: the plots of a review, in order; a plot is shown when one of its columns has data
REVIEW_PLOTS = (
    Plot("energy (J)", ("kinetic_energy", "potential_energy")),
    Plot("contacts", ("contacts",)),
    Plot("iterations", ("iterations",)),
    Plot("tracking residual / hair length", ("residual_rel_max",)),
    Plot("control force / hair weight", ("constraint_force_rel", "control_force_rel")),
)


def choose_plots(with_data: set[str] | frozenset[str], plots=REVIEW_PLOTS) -> list[Plot]:
    """The plots of ``plots`` that have data (a metric column with a finite value), each
    keeping only its columns with data.  A free run's residual and control force are NaN
    for every step: it gets the energies, contacts and iterations."""
    out = []
    for p in plots:
        cols = tuple(c for c in p.columns if c in with_data)
        if cols:
            out.append(Plot(p.title, cols))
    return out


def axis_range(lo: float, hi: float) -> tuple[float, float]:
    """A y range that shows data from ``lo`` to ``hi`` with room, from 0 when the data are
    non-negative (counts, residuals), and never of zero height."""
    lo, hi = float(lo), float(hi)
    if lo >= 0:
        lo = 0.0
    pad = 0.08 * (hi - lo) if hi > lo else max(abs(hi), 1.0) * 0.5
    return lo - (pad if lo < 0 else 0.0), hi + pad


def key_window(t_key: float, t_end: float, half: float = KEY_HALF_WINDOW) -> tuple[float, float]:
    """The window ``[t_key - half, t_key + half]`` inside ``[0, t_end]``."""
    return max(0.0, t_key - half), min(float(t_end), t_key + half)
