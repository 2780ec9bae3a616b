"""Entry point of the perception process: ``python -m hil.perception.child FD NOTIFY_FD PARENT_PID``
(started by :class:`hil.perception.process.PerceptionProcess`; FD is its end of the channel socket,
NOTIFY_FD the write end of the notification pipe)."""

from __future__ import annotations

import sys

from hil.childproc import run_child
from hil.perception.worker import perception_main


def main(argv: list[str]) -> int:
    """Run the perception process on the channel FD and the pipe NOTIFY_FD for the parent
    PARENT_PID (``argv``); 2 with a usage line on other arguments
    (:func:`hil.childproc.run_child`)."""
    return run_child(argv, "hil.perception.child", ("NOTIFY_FD",), perception_main)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
