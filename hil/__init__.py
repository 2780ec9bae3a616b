"""needle-guide HIL controller core: geometry, vision, state machine, safety, CLI.

The core knows no concrete device: it talks to cameras, robots and trackers only through the
interfaces in :mod:`drivers.interfaces`. Units inside the core are millimetres and radians.
"""

__version__ = "0.1.0"
