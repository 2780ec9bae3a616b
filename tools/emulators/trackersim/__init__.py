"""Byte-exact serial emulators of magnetic trackers on a pseudo-terminal.

Ascension Flock of Birds (:mod:`.fob_device`) and NDI Aurora (:mod:`.aurora_device`), producing
poses from a pluggable :class:`.poses.PoseSource`, with injectable faults (:mod:`.faults`).
Run ``tools/trackersim --protocol fob|aurora``; see docs/trackers.md.
"""
