"""Several fields of the RTDE state stream read from one packet.

ur-rtde's receive thread writes a whole data packet into its robot state under one lock, and each
getter (``getSafetyStatusBits``, ``getRuntimeState``, ...) takes that lock for its own field. Two
getters called one after the other can therefore see two packets: a protective stop that also
pauses the control script can be read as "safety normal, script not running" -- the safety bits
from the packet before, the runtime state from the packet with the stop -- and be reported as a
stopped program instead of the protective stop it is (seen in an end-to-end test against
tools/ursim, 1 run in several hundred).

Every packet carries the controller's ``timestamp``, which rises with each packet. Getters called
between two readings of it that are equal all saw the same packet: :func:`one_packet` reads the
timestamp, the fields, the timestamp again, and retries while a packet arrived in between.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")

#: Reads of the fields before :func:`one_packet` gives up. A packet arrives every 2 ms (e-Series;
#: 8 ms CB3) and a read takes tens of microseconds, so a retry is rare and eight in a row mean the
#: reads themselves take about a period each (a starved process): the state is then not read.
READ_TRIES = 8


def one_packet(timestamp: Callable[[], float], read: Callable[[], T],
               tries: int = READ_TRIES) -> tuple[float, T] | None:
    """``(timestamp, read())`` with every getter ``read`` calls taken from the same state packet,
    or None when a new packet arrived during each of ``tries`` attempts. Blocks only as long as
    the getters do; raises what they raise."""
    for _ in range(tries):
        ts = float(timestamp())
        fields = read()
        if float(timestamp()) == ts:
            return ts, fields
    return None
