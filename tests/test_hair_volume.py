"""The volumetric hair-hair model (``collision.hair_hair_model=volume``,
hairexp/physics/hair_volume.py): conservation and dissipation of its friction, its pressure
gradient against finite differences, its response to over-dense hair, its limits and a run."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from hairexp.app.config import compose_config
from hairexp.app.validate import validate_config
from hairexp.errors import InputError, SimulationError
from hairexp.physics import hair_volume as hv_mod
from hairexp.physics.hair_volume import HairVolume


def _hair(V, seed=0, kinematic=None):
    rng = np.random.default_rng(seed)
    m = rng.uniform(0.5e-5, 2e-5, V)
    k = np.zeros(V, dtype=bool) if kinematic is None else kinematic
    return SimpleNamespace(masses=m, kinematic=k), rng


def test_friction_conserves_momentum_and_never_adds_kinetic_energy():
    s, rng = _hair(500)
    x = rng.uniform(0, 0.05, (500, 3))
    v = rng.normal(size=(500, 3))
    hv = HairVolume(s, 0.01, friction=5.0, pressure_speed=0.0)
    out, pressed = hv.apply(x, v, 0.04)
    m = s.masses[:, None]
    np.testing.assert_allclose((m * out).sum(0), (m * v).sum(0), rtol=1e-12, atol=1e-18)
    ke = lambda u: 0.5 * float((m * u ** 2).sum())   # noqa: E731
    assert ke(out) < ke(v) and pressed == 0
    assert np.abs(out - v).max() > 1e-3                 # it did act


def test_a_uniform_motion_is_left_alone():
    s, rng = _hair(300)
    x = rng.uniform(0, 0.05, (300, 3))
    v = np.tile([0.3, -1.0, 0.2], (300, 1))
    out, _ = HairVolume(s, 0.01, 5.0, 0.0).apply(x, v, 0.04)
    np.testing.assert_allclose(out, v, rtol=0, atol=1e-13)


def test_kinematic_roots_drag_but_are_not_moved():
    kin = np.zeros(200, dtype=bool)
    kin[:20] = True
    s, rng = _hair(200, kinematic=kin)
    x = rng.uniform(0, 0.03, (200, 3))
    v = np.zeros((200, 3))
    v[kin] = [1.0, 0.0, 0.0]
    out, _ = HairVolume(s, 0.01, 5.0, 0.0).apply(x, v, 0.04)
    np.testing.assert_array_equal(out[kin], v[kin])
    assert out[~kin, 0].mean() > 0                      # the free hair is dragged along


def test_pressure_gradient_matches_finite_differences():
    rng = np.random.default_rng(3)
    h = 0.01
    dims = np.array([7, 8, 9], dtype=np.int64)
    M = rng.uniform(0, 3, int(dims.prod()))          # cell masses over M_0 = 1: p = max(M - 1, 0)
    P = np.zeros((len(M), 3))
    origin = np.zeros(3)
    x = rng.uniform(0.015, 0.045, (50, 3))

    def fields(y):
        i0 = np.empty(y.shape, dtype=np.int64)
        f = np.empty(y.shape)
        hv_mod._cell_weights(y, origin, 1 / h, i0, f)
        vg, pv, gp = np.empty(y.shape), np.empty(len(y)), np.empty(y.shape)
        hv_mod._gather(i0, f, dims, M, P, 1.0, 1 / h, vg, pv, gp)
        return pv, gp

    _, gp = fields(x)
    eps = 1e-7
    for a in range(3):
        e = np.zeros(3)
        e[a] = eps
        fd = (fields(x + e)[0] - fields(x - e)[0]) / (2 * eps)
        np.testing.assert_allclose(gp[:, a], fd, rtol=1e-5, atol=1e-4)


def test_over_dense_hair_is_pushed_out():
    """The first state sets rho_0; hair gathered denser than that is pushed down the density
    gradient, away from the clump."""
    s, rng = _hair(400)
    hv = HairVolume(s, 0.01, friction=0.0, pressure_speed=0.1)
    spread = rng.uniform(0, 0.1, (400, 3))
    hv.apply(spread, np.zeros((400, 3)), 0.04)          # rho_0 from the spread hair
    centre = np.array([0.05, 0.05, 0.05])
    clump = centre + rng.normal(scale=0.004, size=(400, 3))
    out, pressed = hv.apply(clump, np.zeros((400, 3)), 0.04)
    assert pressed > 300
    outward = np.einsum("ij,ij->i", out, clump - centre)
    assert (outward > 0).mean() > 0.8
    assert np.linalg.norm(out, axis=1).max() <= 0.01 / 0.04 * (1 + 1e-12)   # at most a cell per step


def test_a_grid_too_large_is_refused():
    s, rng = _hair(10)
    x = rng.uniform(0, 1.0, (10, 3))
    x[0] = [1e3, 1e3, 1e3]
    with pytest.raises(SimulationError, match="volume_cell"):
        HairVolume(s, 0.01, 1.0, 0.1).apply(x, np.zeros((10, 3)), 0.04)


@pytest.mark.parametrize("key,value", [("collision.volume_cell", "0"), ("collision.volume_friction", "-1"),
                                       ("collision.volume_pressure_speed", "nan")])
def test_bad_volume_settings_name_the_key(key, value):
    cfg = compose_config(["experiment=goaling_smoke", "collision=hair_hair", "collision.hair_hair_model=volume",
                          f"{key}={value}"])
    with pytest.raises(InputError, match=key.replace(".", r"\.")):
        validate_config(cfg)


def test_a_run_with_the_volume_model(tmp_path):
    from hairexp.app.run import run

    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "frames=3", "logging=off",
                          "collision=hair_hair", "collision.hair_hair_model=volume"])
    s = run(cfg, tmp_path / "run")
    assert s["status"] == "completed" and s["converged"]
    with np.load(tmp_path / "run" / "result.npz") as r:
        assert np.isfinite(r["positions"]).all()


def test_the_volume_acts_once_a_step_over_the_whole_step(tmp_path, monkeypatch):
    """Under TR-BDF2 (two stages) the volume's friction and pressure act after the last stage,
    with the step's dt (not the stage's)."""
    from hairexp.app.run import run

    calls = []
    orig = HairVolume.apply
    monkeypatch.setattr(HairVolume, "apply", lambda self, x, v, dt: calls.append(dt) or orig(self, x, v, dt))
    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "frames=2", "logging=off", "solver.integrator=trbdf2",
                          "collision=hair_hair", "collision.hair_hair_model=volume", "solver.dt=0.04"])
    s = run(cfg, tmp_path / "run")
    assert s["status"] == "completed"
    assert calls and len(calls) == s["steps"] and all(abs(c - 0.04) < 1e-12 for c in calls)
