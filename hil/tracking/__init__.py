"""Tracker calibration in the core: pivot calibration of a stylus/needle sensor and the
registration of the tracker frame to the optical frame by stylus touches (seed 003 section 4.2).
No driver imports: the tracker is reached through :class:`drivers.interfaces.PoseTracker`-like
objects only."""
