"""Simulated devices sharing one deterministic simulated world (patient, robot, cameras, tracker)."""
