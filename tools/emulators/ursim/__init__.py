"""UR controller emulator for the ``ur-rtde`` client: RTDE 30004, primary / secondary / realtime
(script) 30001-30003, dashboard 29999,
fault control 30200. Run it as a separate process: ``tools/ursim`` (see docs/ursim.md)."""
