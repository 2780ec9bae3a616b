"""The servo loop: the one owner of the arm at its control rate (see docs/architecture.md)."""
