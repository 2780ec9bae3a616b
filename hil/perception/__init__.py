"""Perception (grab, locate, triangulate) in its own process, publishing marker sets through
shared memory (docs/architecture.md, "Perception process")."""
