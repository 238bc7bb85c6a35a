"""Frozen scene data (never changes during a run): strands at rest, material, the body's rigid
motion or a dynamic block's parameters, colliders (signed distance shapes), and the procedural
builders.  Imports nothing above it but hairexp.errors."""

from hairexp.model.colliders import SHAPES
from hairexp.model.dynamic_body import DynamicBody
from hairexp.model.rigid import RigidMotion
from hairexp.model.scene import Material, Scene
from hairexp.model.strands import Strands

__all__ = ["SHAPES", "DynamicBody", "Material", "RigidMotion", "Scene", "Strands"]
