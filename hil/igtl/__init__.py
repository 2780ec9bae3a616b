"""OpenIGTLink (3D Slicer / SlicerIGT) streaming of the guide, the registration and the tracker
sensors. Optional: needs the ``igtl`` extra (pyigtl). See docs/igtl.md."""

from hil.igtl.config import IgtlConfig
from hil.igtl.snapshot import IgtlSnapshot, guide_in_image, snapshot_from_controller

__all__ = ["IgtlConfig", "IgtlSnapshot", "guide_in_image", "snapshot_from_controller"]
