"""The benchmarks' Celia config (``experiments.common.celia_bench``) passes a run's checks.

The jerk moves the body (the roots) 12 cm up and 10 cm sideways; Celia's own head collider
stays still, so with it the roots passed through the head, which ``check_clear_roots`` refuses
(session of 2026-12-07: every Celia benchmark stopped with "collider 'head': the hair's roots go
into it" before its first step).  The benchmarks' head moves with the body."""

from __future__ import annotations

import numpy as np
import pytest

from hairexp.app.assemble import check_config
from hairexp.errors import InputError
from hairexp.app.builders import build_scene

from experiments.common import celia_bench, compose, head_collider


@pytest.mark.parametrize("controller,collision", [("free", "off"), ("tracking", "off"), ("free", "default"),
                                                   ("free", "hair_hair")])
def test_celia_bench_config_passes_the_run_checks(controller, collision):
    cfg = celia_bench(controller, steps=30, collision=collision)
    check_config(cfg)                                    # raises InputError if the roots enter a collider
    names = [str(c.name) for c in cfg.scene.colliders]
    assert names == ["head"]


def test_the_bench_head_moves_with_the_roots():
    cfg = celia_bench("free", steps=30)
    scene = build_scene(cfg.scene)
    head = scene.colliders[0]
    for t in (0.0, 0.08, 0.13, 0.5, 1.15, 1.25, 2.0):
        R_b, T_b = scene.motion.pose(t)
        R_h, T_h = head.motion.pose(t)
        np.testing.assert_allclose(R_h, R_b, atol=1e-12)
        np.testing.assert_allclose(T_h, T_b, atol=1e-12)
    assert np.linalg.norm(scene.motion.pose(2.0)[1] - scene.motion.pose(0.0)[1]) > 0.15   # it does jerk


def test_celia_own_head_with_the_jerk_is_refused():
    """The check the benchmark config now passes can fail: the jerk with Celia's still head."""
    cfg = celia_bench("free", steps=30, typed=[
        "scene.colliders=[{name: head, shape: sphere, radius: 0.085, thickness: 0.002, friction: 0.3}]"])
    with pytest.raises(InputError, match="roots go into it"):
        check_config(cfg)


def test_head_collider_is_a_typed_override():
    assert head_collider(compose(["experiment=celia"])).startswith("scene.colliders=[{name: head")


def test_the_trbdf2_cost_probe_takes_what_the_simulator_passes_a_stage():
    """experiments/trbdf2_cost.py swaps its own ``stage`` in for ``Simulator._stage``; when the
    simulator began passing ``last=`` the script stopped at its first step with a TypeError
    (found 2026-12-07).  The probe must accept every parameter ``_stage`` has."""
    import inspect

    from hairexp.physics.simulator import Simulator

    from experiments.trbdf2_cost import StageProbe

    want = list(inspect.signature(Simulator._stage).parameters)[1:]
    have = inspect.signature(StageProbe.stage).parameters
    assert [p for p in want if p not in have] == []
    assert all(have[p].default is not inspect.Parameter.empty for p in want
               if inspect.signature(Simulator._stage).parameters[p].default is not inspect.Parameter.empty)
