"""Vision: stereo calibration, ring-marker detection, stereo matching, synthetic rendering."""
