"""An experiment's variants settle once (``hairexp.app.assemble._settled``, within
``shared_settle``, which ``run_experiment`` opens): a run whose scene, solver and collision
settings are those of the last run settled there starts from a copy of its settled scene; any
difference in them settles again; outside it every run settles."""

from __future__ import annotations

import importlib

import numpy as np

from hairexp.app import compose_config

assemble_mod = importlib.import_module("hairexp.app.assemble")

BASE = ["experiment=goaling_smoke", "variants=[]", "frames=2", "scene.settle=0.4"]


def test_variants_that_differ_in_their_controller_settle_once(monkeypatch):
    calls = []
    real = assemble_mod.settle_scene

    def counting(scene, cfg):
        calls.append(float(cfg.solver.rtol))
        return real(scene, cfg)

    monkeypatch.setattr(assemble_mod, "settle_scene", counting)
    assemble_mod.assemble(compose_config([*BASE, "controller=free"]))      # outside: not kept
    assemble_mod.assemble(compose_config([*BASE, "controller=free"]))
    assert len(calls) == 2 and assemble_mod._SHARED is None
    calls.clear()
    with assemble_mod.shared_settle():
        free = assemble_mod.assemble(compose_config([*BASE, "controller=free"]))
        tracked = assemble_mod.assemble(compose_config([*BASE, "controller=tracking"]))
    assert len(calls) == 1
    a, b = free.scene, tracked.scene
    assert float(free.cfg.scene.settle) > 0
    np.testing.assert_array_equal(a.initial_positions(), b.initial_positions())
    assert not np.shares_memory(a.root_body, b.root_body)          # a copy: neither run can change the other's
    # the settled state is the one a fresh settle gives
    again = assemble_mod.assemble(compose_config([*BASE, "controller=tracking"]))
    np.testing.assert_array_equal(again.scene.initial_positions(), b.initial_positions())
    assert len(calls) == 2
    with assemble_mod.shared_settle():   # a solver setting the settle reads: settled again
        assemble_mod.assemble(compose_config([*BASE, "controller=tracking"]))
        assemble_mod.assemble(compose_config([*BASE, "controller=tracking", "solver.rtol=1e-6"]))
    assert calls == [1e-5, 1e-5, 1e-5, 1e-6]


def test_variants_share_one_guide_simulation_attached_to_their_own_body(monkeypatch):
    """Simulated guides (``guides.source=simulated``) are simulated once within
    ``shared_settle`` for runs with equal settings; each run's animation is a copy attached to its
    own scene's body motion, equal to a fresh simulation; a different guides key simulates again."""
    calls = []
    real = assemble_mod.source_guides

    def counting(cfg, scene, frames, fps):
        calls.append(int(cfg.guides.n_vertices))
        return real(cfg, scene, frames, fps)

    monkeypatch.setattr(assemble_mod, "source_guides", counting)
    sim = [*BASE, "guides.source=simulated", "guides.count=2", "guides.n_vertices=6"]
    with assemble_mod.shared_settle():
        a = assemble_mod.assemble(compose_config([*sim, "controller=free"]))
        b = assemble_mod.assemble(compose_config([*sim, "controller=tracking"]))
        assemble_mod.assemble(compose_config([*sim, "controller=tracking", "guides.n_vertices=7"]))
    assert calls == [6, 7]
    fresh = assemble_mod.assemble(compose_config([*sim, "controller=tracking"]))
    assert calls == [6, 7, 6]
    assert b.guides.motion is b.scene.motion and a.guides.motion is a.scene.motion
    assert not np.shares_memory(a.guides.frames, b.guides.frames)
    np.testing.assert_array_equal(b.guides.frames, fresh.guides.frames)
    for t in (0.0, 0.03, 0.07):
        np.testing.assert_array_equal(b.guides.shape_at(t), fresh.guides.shape_at(t))


def test_an_experiment_checks_each_variant_once(monkeypatch, tmp_path):
    """``run_experiment`` checks every variant's config (``check_config``: its scene, guides and
    controller built) before the first runs; the variant's run does not check it again
    (``run_checked``), while ``run`` on its own does."""
    from hairexp.app import experiment as experiment_mod
    from hairexp.app import run as run_mod

    calls = []
    real = assemble_mod.check_config

    def counting(cfg, files=True):
        calls.append(str(getattr(cfg.controller.name, "value", cfg.controller.name)))
        return real(cfg, files)

    monkeypatch.setattr(experiment_mod, "check_config", counting)
    monkeypatch.setattr(run_mod, "check_config", counting)
    cfg = compose_config(["experiment=goaling_smoke", "frames=2", "logging=off"])
    assert [str(v.name) for v in cfg.variants] == ["free", "tracked"]
    summary = experiment_mod.run_experiment(cfg, tmp_path / "exp")
    assert summary["status"] == "completed"
    assert sorted(calls) == ["free", "tracking"]
    calls.clear()
    run_mod.run(compose_config(["experiment=goaling_smoke", "variants=[]", "frames=2", "logging=off"]), tmp_path / "one")
    assert len(calls) == 1
