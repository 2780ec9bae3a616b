"""File input for the core: point lists (and later plans) from the files planning software writes."""

from hil.io.points import PointSet, read_points

__all__ = ["PointSet", "read_points"]
