"""config -> Scene: the builder ``scene.builder`` names (procedural ``wisp`` and ``ponytail``,
hairexp/model/builders.py, or a USD stage, hairexp/io/usd_read.py), then the dynamic body."""

from __future__ import annotations

from hairexp.model.builders import build_procedural_scene, with_dynamic_body
from hairexp.model.scene import Scene


def build_scene(cfg) -> Scene:
    """The Scene of ``cfg`` (the ``scene`` config group), at rest and unsettled."""
    builder = str(getattr(cfg.builder, "value", cfg.builder))
    if builder == "usd":  # a user's USD stage (pxr is imported only then)
        from hairexp.io.usd_read import build_usd_scene

        return with_dynamic_body(cfg, build_usd_scene(cfg))
    return with_dynamic_body(cfg, build_procedural_scene(cfg))
