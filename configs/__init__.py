"""Hardware setups as files (package data, so that an installed ``hil`` finds ``sim.toml``)."""
