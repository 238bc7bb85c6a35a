"""Findings of the independent probe rounds 29 (weak, W2) and 30 of issue 12, fixed."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hairexp.app import compose_config
from hairexp.app.assemble import assemble_scene, check_clear_roots, check_config
from hairexp.errors import InputError


def test_a_collider_on_the_bodys_path_is_refused_before_the_run():
    """A wheel of radius 0.5 m in goaling: the body carries the roots into it (the first root 16 mm
    deep at t = 0.68 s).  It ran "completed" with the hair stretched by 518 % and the tracked
    variant took 85 s for 21 steps (round 29, W2); now the check before the run names it."""
    cfg = compose_config(["experiment=goaling_smoke", "variants=[]", "scene.colliders.0.radius=0.5"])
    with pytest.raises(InputError, match=r"^scene\.colliders\[0\]: collider 'wheel': the hair's roots go "
                                         r"into it \(strand \d+ root by [\d.]+ mm at t = [\d.]+ s\)"):
        check_config(cfg)


def test_roots_that_start_inside_a_collider_moving_with_them_are_allowed():
    """celia's scalp roots lie up to 7 mm inside the head sphere, which moves with the body: the
    depth does not grow, so the scene is not refused; the head moving back into the roots while
    the body stays still takes them deeper, and is."""
    cfg = compose_config(["experiment=celia_smoke", "variants=[]"])
    cfg, scene, _ = assemble_scene(cfg, settle=False)
    head = next(c for c in scene.colliders if c.name == "head")
    k = scene.strands.kinematic
    assert head.sdf_body(head.to_body(scene.root_positions(0.0)[k], 0.0)).min() < -1e-3   # the premise
    check_clear_roots(scene, int(cfg.frames), float(cfg.fps), 1)
    from hairexp.model.rigid import RigidMotion

    # the head moving 5 cm back into the ponytail's roots (at z = -9 cm) in 0.5 s, the body still
    head.motion = RigidMotion(np.array([0.0, 0.5]), np.array([[0, 0, 0], [0, 0, -0.05]]), np.zeros((2, 3)), "linear")
    scene = dataclasses.replace(scene, motion=RigidMotion.static())
    with pytest.raises(InputError, match=r"collider 'head': the hair's roots go into it \(strand \d+ "
                                         r"root by [\d.]+ mm at t = 0\.[01]"):
        check_clear_roots(scene, int(cfg.frames), float(cfg.fps), 1)
