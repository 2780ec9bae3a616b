"""Entry point of the servo process: ``python -m hil.servo.child FD PARENT_PID`` (started by
:class:`hil.servo.process.ServoProcess`; FD is its end of the channel socket)."""

from __future__ import annotations

import sys

from hil.childproc import run_child
from hil.servo.process import servo_main


def main(argv: list[str]) -> int:
    """Run the servo process on the channel FD for the parent PARENT_PID (``argv``); 2 with a
    usage line on other arguments (:func:`hil.childproc.run_child`)."""
    return run_child(argv, "hil.servo.child", (), servo_main)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
