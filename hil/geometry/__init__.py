"""Geometry core: rigid transforms, registration, error prediction, ICP, marker matching,
triangulation. numpy in, numpy out, millimetres and radians."""

from hil.geometry.transform import RigidTransform

__all__ = ["RigidTransform"]
