"""Device emulators the project ships (run them as separate processes; see docs/)."""
