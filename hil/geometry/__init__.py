"""Geometry core: rigid transforms, registration, error prediction, ICP, marker matching,
triangulation. numpy in, numpy out, millimetres and radians."""

from hil.geometry.registration import Registration, register_horn, register_svd
from hil.geometry.transform import RigidTransform
from hil.geometry.tre import expected_tre_mm

__all__ = ["Registration", "RigidTransform", "expected_tre_mm", "register_horn", "register_svd"]
