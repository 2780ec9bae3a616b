"""Fault injection: wrappers that add scheduled faults to any driver, real or simulated."""
