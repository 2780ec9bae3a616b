"""Entry point of the servo process: ``python -m hil.servo.child FD PARENT_PID`` (started by
:class:`hil.servo.process.ServoProcess`; FD is its end of the channel socket)."""

from __future__ import annotations

import sys
from multiprocessing.connection import Connection

from hil.servo.process import servo_main


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        sys.stderr.write("usage: python -m hil.servo.child FD PARENT_PID (started by hil, not by hand)\n")
        return 2
    servo_main(Connection(int(argv[0])), int(argv[1]))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
