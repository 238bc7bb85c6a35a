"""Findings of the independent probe round 36 of issue 12, fixed."""

from __future__ import annotations

import pytest


@pytest.mark.parametrize("overrides, unused", [
    # (the launch's overrides, whether its key -- the last override's -- is named as not used)
    (["collision.hair_thickness=0.009"], True),   # goaling: the object stage, no hair-hair: nothing reads it
    (["collision.hair_hair=true", "collision.hair_thickness=0.009"], False),
    (["collision.contact=barrier", "collision.hair_thickness=0.009"], False),
    (["collision.hair_hair=true", "collision.hair_hair_model=volume", "collision.hair_thickness=0.009"], True),
    (["scene.settle=0", "scene.settle_dt=0.5"], True),
    (["scene.settle=0.4", "scene.settle_dt=0.02"], False),
    (["solver.derivatives=autograd", "solver.compile=on"], True),
    (["solver.compile=on"], False),
    (["solver.kernels=torch", "solver.threads=2"], True),
    (["solver.derivatives=autograd", "solver.kernels=numba", "solver.threads=2"], True),
    (["solver.threads=2"], False),
    (["scene.usd_body=/Foo"], True),
    (["scene.usd_hair=/Nowhere"], True),
    (["collision.objects=false", "collision.max_travel=0.9"], True),
    (["collision.max_travel=0.9"], False),
    (["collision.friction=false"], True),   # the stage applies each collider's friction whatever it says
    (["collision.contact=barrier", "collision.friction=false"], False),
])
def test_settings_no_run_reads_are_named(overrides, unused):
    """Keys accepted without a word though nothing of the run read them (round 36, bad F1-F6 and
    the undecided collision.friction); each is named where it is not read, and only there."""
    from hairexp.app import compose_config
    from hairexp.app.validate import unused_settings

    cfg = compose_config(["experiment=goaling_smoke", "variants=[]"] + overrides)
    key = overrides[-1].split("=", 1)[0]
    named = [u for u in unused_settings([cfg], [o.split("=", 1)[0] for o in overrides]) if u.startswith(f"{key} (")]
    assert bool(named) == unused, (overrides, named)
