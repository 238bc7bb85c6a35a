"""The tracking controller, paper 3: correspondence (3.1, ``correspondence``), COM constraints
with targets in parallel-transported frames sliding on the guide splines (3.2,
``constraints``), variance control (3.3, ``variance``), the KKT solves (eq. 8, ``kkt``) and the
SQP (3.4, ``sqp``), put together in ``controller.TrackingController``."""

from __future__ import annotations

from hairexp.control.tracking.controller import TrackingController


def build(cfg, scene, guides) -> TrackingController:
    return TrackingController(scene, guides, cfg.tracking)
