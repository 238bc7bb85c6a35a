"""Helpers for the USD tests: a small tracked scene config with colliders, its stage in the input
layout, the ``from_usd`` config that reads it back, and in-place edits of a stage on disk."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from omegaconf import OmegaConf
from tracking_helpers import tracked_cfg

from hairexp.app.config import ColliderConfig
from hairexp.io.usd_write import write_scene_usd
from hairexp.app.builders import build_scene
from hairexp.app.guides import build_guides

FRAMES = 5
N_STRANDS, N_VERTICES, N_GUIDES, GUIDE_VERTICES = 6, 8, 2, 6

#: Linear body motion with keyframes on frame times (0, 2 and 5 at 25 fps): translation and rotation.
MOTION = {
    "scene.motion.interpolation": "linear",
    "scene.motion.times": [0.0, 0.08, 0.2],
    "scene.motion.translations": [[0.0, 0.0, 0.0], [0.02, 0.01, 0.0], [0.05, 0.0, 0.01]],
    "scene.motion.rotations_deg": [[0.0, 0.0, 0.0], [0.0, 10.0, 0.0], [5.0, 20.0, 0.0]],
}


def still(pos, rot=(0.0, 0.0, 0.0)) -> dict:
    return {"times": [0.0], "translations": [list(pos)], "rotations_deg": [list(rot)]}


#: One collider of every shape; the ball moves into the hair (linear keys on frames 0 and 5).
COLLIDERS = [
    {"name": "ball", "shape": "sphere", "radius": 0.03, "thickness": 0.003, "friction": 0.5,
     "motion": {"interpolation": "linear", "times": [0.0, 0.2], "translations": [[0.05, -0.2, 0.0], [0.0, -0.2, 0.0]],
                "rotations_deg": [[0.0, 0.0, 0.0], [0.0, 0.0, 30.0]]}},
    {"name": "crate", "shape": "box", "half_extents": [0.05, 0.02, 0.03],
     "motion": still([0.4, -0.5, 0.0], (0.0, 30.0, 0.0))},
    {"name": "wheel", "shape": "cylinder", "radius": 0.05, "half_height": 0.02, "spin": 3.0, "friction": 0.8,
     "motion": still([-0.4, -0.5, 0.0], (90.0, 0.0, 0.0))},
    {"name": "pole", "shape": "capsule", "radius": 0.01, "half_length": 0.1, "thickness": 0.0,
     "motion": still([0.0, -0.5, 0.4])},
    {"name": "floor", "shape": "plane", "motion": still([0.0, -1.0, 0.0])},
]


def scene_overrides() -> dict:
    """Dotted overrides of a small tracked goaling-like scene (6 x 8 wisp, 2 scaled guides).

    Strain limiting after contacts is off here and in the re-imported runs: it amplifies the
    float32 rounding of USD points to ~1 mm differences after a contact (measured: 0.78 mm on
    this scene), which would hide whether the exchange itself loses anything."""
    return {
        "scene.name": "usd_test", "scene.n_strands": N_STRANDS, "scene.n_vertices": N_VERTICES,
        "scene.length": 0.3, "scene.spread": 0.1, "guides.count": N_GUIDES, "guides.n_vertices": GUIDE_VERTICES,
        "guides.source": "scaled", "guides.scale_times": [0.0, 0.2], "guides.scale_factors": [1.0, 0.8],
        "tracking.points_per_guide": 4, "frames": FRAMES, "guides.edits": [], "collision.strain_limit": 0.0, **MOTION,
    }


def set_colliders(cfg, colliders=COLLIDERS) -> None:
    """Put collider dicts into ``cfg.scene.colliders`` (typed as ColliderConfig)."""
    nodes = [OmegaConf.merge(OmegaConf.structured(ColliderConfig), c) for c in colliders]
    OmegaConf.update(cfg, "scene.colliders", nodes, merge=False)


def source_cfg(colliders=COLLIDERS, **extra):
    """Structured config of the source scene (no Hydra)."""
    cfg = tracked_cfg({**scene_overrides(), **extra})
    set_colliders(cfg, colliders)
    return cfg


def write_stage(path: Path, cfg) -> tuple:
    """Build ``cfg``'s scene and guides, write them in the input layout: (scene, guides)."""
    scene = build_scene(cfg.scene)
    guides = build_guides(cfg, scene, cfg.frames, cfg.fps)
    write_scene_usd(path, scene, guides, cfg.fps, cfg.frames)
    return scene, guides


def usd_cfg(path: Path, **extra):
    """Structured ``from_usd``-like config reading ``path`` (frames and fps from the stage)."""
    return tracked_cfg({"scene.name": "from_usd", "scene.builder": "usd", "scene.usd": str(path),
                        "guides.source": "usd", "tracking.points_per_guide": 4, "frames": None, "fps": None,
                        **extra})


def edit_stage(path: Path, edit) -> None:
    """Open the stage at ``path``, apply ``edit(stage)`` and save it in place."""
    from pxr import Usd

    stage = Usd.Stage.Open(str(path))
    edit(stage)
    stage.GetRootLayer().Save()


def vec3f(points) -> object:
    from pxr import Vt

    return Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points, dtype=np.float32))
