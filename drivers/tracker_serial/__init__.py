"""Magnetic trackers over a serial port (``pyserial``): Ascension Flock of Birds, NDI Aurora."""
