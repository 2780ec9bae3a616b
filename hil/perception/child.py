"""Entry point of the perception process: ``python -m hil.perception.child FD NOTIFY_FD PARENT_PID``
(started by :class:`hil.perception.process.PerceptionProcess`; FD is its end of the channel socket,
NOTIFY_FD the write end of the notification pipe)."""

from __future__ import annotations

import sys
from multiprocessing.connection import Connection

from hil.perception.worker import perception_main


def main(argv: list[str]) -> int:
    if len(argv) != 3:
        sys.stderr.write("usage: python -m hil.perception.child FD NOTIFY_FD PARENT_PID (started by hil, "
                         "not by hand)\n")
        return 2
    perception_main(Connection(int(argv[0])), int(argv[1]), int(argv[2]))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
