"""Controllers: what drives the hair beyond its own physics (the interface the step calls is
hairexp/physics/controller.py).  Each controller is one module with a ``build(cfg, scene,
guides)`` factory, registered here by its ``controller.name``; the config schema's choices
(hairexp/app/config.py) are this registry's keys.

| name | module | what |
|---|---|---|
| ``free`` | ``free`` | the hair's physics alone (Newton on eq. 5) |
| ``tracking`` | ``tracking`` | paper 3: COM constraints on the guides, SQP (3.1-3.4) |
| ``skinned`` | ``skinned`` | baseline: detail hair skinned to the guides, no simulation |
| ``attract`` | ``attract`` | baseline: free simulation plus springs to the skinned positions |
"""

from __future__ import annotations

from importlib import import_module

from hairexp.errors import InputError

#: controller.name -> the module whose ``build(cfg, scene, guides)`` makes it
REGISTRY = {
    "free": "hairexp.control.free",
    "tracking": "hairexp.control.tracking",
    "skinned": "hairexp.control.skinned",
    "attract": "hairexp.control.attract",
}


def build_controller(name: str, cfg, scene, guides):
    """The controller ``name`` of a run (``cfg``: the run's config, ``scene``, ``guides``)."""
    if name not in REGISTRY:
        raise InputError(f"unknown controller {name!r} (one of {', '.join(REGISTRY)})", "controller.name")
    return import_module(REGISTRY[name]).build(cfg, scene, guides)
