"""OpenIGTLink (3D Slicer / SlicerIGT) streaming of the guide, the registration and the tracker
sensors. Optional: needs the ``igtl`` extra (pyigtl). See docs/igtl.md."""

from hil.igtl.config import IgtlConfig
from hil.igtl.snapshot import IgtlSnapshot, igtl_snapshot

__all__ = ["IgtlConfig", "IgtlSnapshot", "igtl_snapshot"]
