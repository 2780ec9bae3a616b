"""The procedure's phases, one module each (see :mod:`hil.controller.phases.base`)."""
