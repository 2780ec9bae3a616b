"""Probe what this machine grants a real-time loop with fixed work and none of the project's code
(hil/soak/probe.py has the method and the figures).

Run: ``tools/bench host [--seconds S] [--rate HZ] [--work-ms MS] [--json]``
"""

from __future__ import annotations

import sys

from hil.soak.probe import main

if __name__ == "__main__":
    sys.exit(main(prog="tools/bench host"))
