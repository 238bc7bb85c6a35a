"""Volumetric hair-hair interaction (``collision.hair_hair_model=volume``): the hair as a
continuum on a grid, after Petrovic, Henne and Anderson 2005 ("Volumetric methods for
simulation and rendering of hair", Pixar TM 06-08) and McAdams, Selle, Ward, Sifakis and Teran
2009 ("Detail preserving continuum simulation of straight hair").  It replaces the edge-edge
contacts of ``collisions.HairHair`` where their cost is too high: a production groom's hair-hair
interaction as friction and pressure of the hair volume, O(vertices) per step, with no edge
pairs.

A velocity filter (Petrovic et al. 2005, sec. 3.2: the hair's velocities are filtered on the
grid and the next implicit solve carries the change into the positions): once per step, after
the solve of its last stage (``Simulator._stage``) and before the object contacts, with the
solve's end positions x and the scheme's end velocities v of every vertex, kinematic roots
included:

1. splat mass and momentum onto a regular grid of cell size ``cell`` with trilinear weights
   w_ic (sum_c w_ic = 1): M_c = sum_i w_ic m_i, P_c = sum_i w_ic m_i v_i; the grid velocity
   V_c = P_c / M_c and the density rho_c = M_c / cell^3;
2. friction (Petrovic et al. 2005, sec. 3.2, as a rate): each free vertex's velocity is blended
   toward the grid velocity interpolated at it, v_i += (1 - exp(-friction dt)) (V(x_i) - v_i).
   Over all vertices this conserves momentum exactly (sum_i m_i V(x_i) = sum_c V_c M_c =
   sum_i m_i v_i) and does not increase the kinetic energy (a mass-weighted average);
3. pressure (McAdams et al. 2009, sec. 4, the hair as a compressible fluid with equation of state
   P = c^2 (rho - rho_0) where rho > rho_0): Euler's dv/dt = -grad P / rho = -c^2 grad(rho / rho_0)
   over the over-dense cells, integrated over the step at each free vertex:
   v_i -= dt c^2 grad p(x_i), p = max(rho / rho_0 - 1, 0) interpolated trilinearly (its gradient
   from the weights' gradients).  rho_0, the rest density, is the densest cell of the first state seen
   (the groom as built or settled): hair may gather up to the density it started with before
   it pushes back.  Explicit in time: stable while dt c / cell < 1 (c = 0.1 m/s, cell 1 cm:
   dt < 0.1 s), and no vertex takes more than cell / dt from the pressure in one step (hair
   crushed far past rho_0 spreads over several steps).

Only the velocities change (v_{n+1} += dv); the positions the solve produced stay, so every edge
keeps the length the solve gave it.  The object contacts then act on the solve's path as without
the volume; a vertex they touched takes their velocity plus dv, and a vertex on a collider's shell
is filtered by the inelastic contact again (``collisions.contact_velocities``).  The integrator
carries dv into the next step as an impulse at t_{n+1} (``after_velocity_filter``,
hairexp/physics/integrators.py, "Velocity filters": BDF2 shifts its history, TR-BDF2 keeps its
a_0 and does not restart), so the next solve moves each free vertex by about dt dv more, under
its stretch and bending forces.  (Until 2026-12-02 the positions followed the filtered velocities
vertex by vertex, x = x_n + dt v, as the edge contacts' impulses do: that ignored the edges
and stretched the strands, max strain 2.5 % on celia_smoke free against 0.03 % without hair-hair,
and it made TR-BDF2 restart with implicit Euler after every step.)

What is lost against the edge contacts: strands can pass through each other (there is no
edge-edge collision at all), and contact below the cell size is not resolved; what is gained:
cost linear in the vertices, no broad phase.  reports/bench_collisions.md measures both.
"""

from __future__ import annotations

import math

import numpy as np

from hairexp.errors import InputError, SimulationError
from hairexp.physics.kernels import njit

#: The grid is refused above this many cells (the hair spread far apart against a small cell)
MAX_CELLS = 20_000_000

@njit(cache=True)
def _lower_corner(x, h, origin):
    """origin = the points' minimum per axis - h (a cell of margin)."""
    for a in range(3):
        lo = x[0, a]
        for v in range(1, x.shape[0]):
            lo = min(lo, x[v, a])
        origin[a] = lo - h


@njit(cache=True)
def _cell_weights(x, origin, inv_h, i0, f, top):
    """Per point its lower cell index i0 and fraction f in the cell of the grid at ``origin``;
    top = the largest i0 per axis."""
    for a in range(3):
        top[a] = 0
    for v in range(x.shape[0]):
        for a in range(3):
            g = (x[v, a] - origin[a]) * inv_h
            k = math.floor(g)
            i0[v, a] = k
            f[v, a] = g - k
            top[a] = max(top[a], k)


@njit(cache=True)
def _filter(v, vg, pv, gp, movable, blend, dtc2, cap, out):
    """``HairVolume.apply``'s update of each movable vertex's velocity (out = v elsewhere):
    friction out += blend (vg - out), then the pressure's dv = dtc2 grad p capped at ``cap`` in
    norm; returns the movable vertices with p > 0 (when there is pressure)."""
    pressed = 0
    for i in range(v.shape[0]):
        for a in range(3):
            out[i, a] = v[i, a]
        if not movable[i]:
            continue
        if blend > 0:
            for a in range(3):
                out[i, a] += blend * (vg[i, a] - out[i, a])
        if dtc2 != 0.0:
            d0 = dtc2 * gp[i, 0]
            d1 = dtc2 * gp[i, 1]
            d2 = dtc2 * gp[i, 2]
            s = min(1.0, cap / max(math.sqrt(d0 * d0 + d1 * d1 + d2 * d2), 1e-300))
            out[i, 0] += d0 * s
            out[i, 1] += d1 * s
            out[i, 2] += d2 * s
            if pv[i] > 0:
                pressed += 1
    return pressed


@njit(cache=True)
def _splat(i0, f, m, vel, dims, M, P):
    """M_c += w m, P_c += w m v over each vertex's 8 cells (trilinear w)."""
    for v in range(i0.shape[0]):
        for c in range(8):
            w = m[v]
            cx, cy, cz = c >> 2, (c >> 1) & 1, c & 1
            w *= f[v, 0] if cx else 1.0 - f[v, 0]
            w *= f[v, 1] if cy else 1.0 - f[v, 1]
            w *= f[v, 2] if cz else 1.0 - f[v, 2]
            idx = ((i0[v, 0] + cx) * dims[1] + i0[v, 1] + cy) * dims[2] + i0[v, 2] + cz
            M[idx] += w
            for a in range(3):
                P[idx, a] += w * vel[v, a]


@njit(cache=True)
def _gather(i0, f, dims, M, P, inv_rho0_mass, inv_h, vg, pv, gp):
    """Per vertex: the grid velocity vg (P_c / M_c), the pressure pv (p_c = max(M_c / M_0 - 1, 0),
    M_0 = rho_0 cell^3; ``inv_rho0_mass`` = 1 / M_0, 0: no pressure) and its gradient gp,
    trilinear in the cells around it."""
    for v in range(i0.shape[0]):
        for a in range(3):
            vg[v, a] = 0.0
            gp[v, a] = 0.0
        pv[v] = 0.0
        for c in range(8):
            cx, cy, cz = c >> 2, (c >> 1) & 1, c & 1
            wx = f[v, 0] if cx else 1.0 - f[v, 0]
            wy = f[v, 1] if cy else 1.0 - f[v, 1]
            wz = f[v, 2] if cz else 1.0 - f[v, 2]
            idx = ((i0[v, 0] + cx) * dims[1] + i0[v, 1] + cy) * dims[2] + i0[v, 2] + cz
            w = wx * wy * wz
            mc = M[idx]
            if mc > 0:
                for a in range(3):
                    vg[v, a] += w * P[idx, a] / mc
            pc = max(mc * inv_rho0_mass - 1.0, 0.0)
            pv[v] += w * pc
            sx = inv_h if cx else -inv_h
            sy = inv_h if cy else -inv_h
            sz = inv_h if cz else -inv_h
            gp[v, 0] += sx * wy * wz * pc
            gp[v, 1] += wx * sy * wz * pc
            gp[v, 2] += wx * wy * sz * pc


def grid_cells(span, cell: float) -> float:
    """Cells of the grid ``HairVolume._grid`` lays over points spanning ``span`` (3,) m: a cell of
    margin below (origin at the minimum - cell) and cell indices up to floor(span / cell) + 1, so
    floor(span / cell) + 3 cells an axis; a float, inf for a cell too small to count with."""
    return float(np.prod(np.floor(np.asarray(span, dtype=np.float64) / cell) + 3.0))


class HairVolume:
    def __init__(self, strands, cell: float, friction: float, pressure_speed: float):
        """``cell`` (m), ``friction`` (1/s), ``pressure_speed`` c (m/s); see the module doc."""
        self.m = np.asarray(strands.masses, dtype=np.float64)
        self.movable = ~np.asarray(strands.kinematic, dtype=bool)
        self.cell, self.friction, self.c2 = float(cell), float(friction), float(pressure_speed) ** 2
        self.rho0: float | None = None
        # the grid over the hair at rest, before the first step: a cell too small for it is bad
        # input (the check in ``_grid`` stays for hair that spreads later)
        span = np.ptp(np.asarray(strands.rest, dtype=np.float64), axis=0)
        cells = grid_cells(span, self.cell)
        if cells > MAX_CELLS:
            raise InputError(f"the hair volume grid over the hair at rest would have {cells:.3g} cells (more than "
                             f"{MAX_CELLS:,}): the hair spans {span.round(3).tolist()} m and a cell is {self.cell:g} m; "
                             f"use a larger cell", "collision.volume_cell")

    def _grid(self, x: np.ndarray):
        """(origin (3,), lower cell index (V, 3), fraction in the cell (V, 3), dims (3,), cells)."""
        h = self.cell
        x = np.ascontiguousarray(x, dtype=np.float64)
        origin, top = np.empty(3), np.empty(3, dtype=np.int64)
        i0 = np.empty(x.shape, dtype=np.int64)
        f = np.empty(x.shape)
        _lower_corner(x, h, origin)
        _cell_weights(x, origin, 1.0 / h, i0, f, top)
        dims = top + 2
        n = int(np.prod(dims.astype(np.float64)))
        if n > MAX_CELLS:
            raise SimulationError(f"hair volume grid of {dims.tolist()} cells (collision.volume_cell = {h:g} m) is too "
                                  f"large: the hair spans {np.ptp(x, axis=0).round(3).tolist()} m; use a larger cell")
        return i0, f, dims, n

    def fields(self, x: np.ndarray, v: np.ndarray):
        """(grid velocity at each vertex (V, 3), pressure p there (V,), grad p (V, 3)); sets
        rho_0 on the first call (module doc)."""
        i0, f, dims, n = self._grid(x)
        M = np.zeros(n)
        P = np.zeros((n, 3))
        _splat(i0, f, self.m, np.ascontiguousarray(v, dtype=np.float64), dims, M, P)
        if self.rho0 is None:
            self.rho0 = float(M.max()) / self.cell ** 3   # the densest cell (module doc)
        inv_m0 = 1.0 / (self.rho0 * self.cell ** 3) if self.rho0 > 0 else 0.0
        vg, pv, gp = np.empty((len(x), 3)), np.empty(len(x)), np.empty((len(x), 3))
        _gather(i0, f, dims, M, P, inv_m0, 1.0 / self.cell, vg, pv, gp)
        return vg, pv, gp

    def apply(self, x: np.ndarray, v: np.ndarray, dt: float) -> tuple[np.ndarray, int]:
        """(v after friction and pressure, number of free vertices in over-dense cells)."""
        v = np.ascontiguousarray(v, dtype=np.float64)
        vg, pv, gp = self.fields(x, v)
        out = np.empty_like(v)
        blend = 1.0 - math.exp(-self.friction * dt)
        # the pressure's dv = -dt c^2 grad p, at most a cell per step: an explicit pressure step is
        # stable below that (CFL), and hair crushed far past rho_0 (p >> 1) is spread over several
        # steps, not shot out
        dtc2 = -dt * self.c2 if self.c2 > 0 else 0.0
        pressed = _filter(v, vg, pv, gp, self.movable, blend, dtc2, self.cell / dt, out)
        return out, int(pressed)
