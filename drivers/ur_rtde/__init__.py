"""UR3 / UR e-Series arm over RTDE through the ``ur-rtde`` library."""
