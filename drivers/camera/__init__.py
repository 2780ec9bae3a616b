"""Real stereo cameras: Aravis (GigE Vision / USB3 Vision), V4L2, and recorded-session replay."""
