"""Real-time soak of the simulated procedure in compensation (see docs/benchmarks.md)."""
