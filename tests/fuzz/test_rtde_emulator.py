"""RTDE packets from a hostile client, fed to the UR emulator's message parser (tools/emulators/ursim).

The only acceptable outcomes: the message is handled, or the connection is closed as a protocol
violation; the emulator's controller keeps ticking with finite joint values."""

from __future__ import annotations

import asyncio
import struct
import sys
from pathlib import Path
from typing import Any

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

TOOLS = Path(__file__).resolve().parents[2] / "tools"
if str(TOOLS) not in sys.path:
    sys.path.insert(0, str(TOOLS))

from emulators.ursim import protocol as proto  # noqa: E402
from emulators.ursim.controller import ControllerVersion, UrController  # noqa: E402
from emulators.ursim.server import Emulator, Ports, RtdeConnection  # noqa: E402


class _Transport:
    def get_write_buffer_size(self) -> int:
        return 0

    def abort(self) -> None:
        pass


class _Writer:
    def __init__(self) -> None:
        self.transport = _Transport()
        self.sent = bytearray()
        self.closed = False

    def write(self, data: bytes) -> None:
        self.sent += data

    def close(self) -> None:
        self.closed = True


OUT_NAMES = sorted(proto.OUTPUT_TYPES)
IN_NAMES = sorted(proto.INPUT_TYPES)


@st.composite
def messages(draw: st.DrawFn) -> bytes:
    kind = draw(st.sampled_from(["outputs", "inputs", "data", "simple", "raw", "garbage"]))
    if kind == "outputs":
        freq = draw(st.floats(allow_nan=True, allow_infinity=True))
        names = draw(st.lists(st.sampled_from([*OUT_NAMES, "bogus"]), min_size=0, max_size=6))
        return proto.pack(
            proto.CONTROL_PACKAGE_SETUP_OUTPUTS, struct.pack(">d", freq) + ",".join(names).encode()
        )
    if kind == "inputs":
        names = draw(st.lists(st.sampled_from([*IN_NAMES, "bogus"]), min_size=0, max_size=6))
        return proto.pack(proto.CONTROL_PACKAGE_SETUP_INPUTS, ",".join(names).encode())
    if kind == "data":
        rid = draw(st.integers(0, 4))
        body = draw(st.binary(max_size=64))
        if draw(st.booleans()):  # doubles: NaN, inf, huge
            body = b"".join(
                struct.pack(">d", draw(st.floats(allow_nan=True, allow_infinity=True)))
                for _ in range(draw(st.integers(0, 8)))
            )
        return proto.pack(proto.DATA_PACKAGE, bytes([rid]) + body)
    if kind == "simple":
        t = draw(
            st.sampled_from(
                [
                    proto.REQUEST_PROTOCOL_VERSION,
                    proto.GET_URCONTROL_VERSION,
                    proto.TEXT_MESSAGE,
                    proto.CONTROL_PACKAGE_START,
                    proto.CONTROL_PACKAGE_PAUSE,
                ]
            )
        )
        return proto.pack(t, draw(st.binary(max_size=8)))
    if kind == "raw":  # a header with any size and type, then any bytes
        return proto.HEADER.pack(draw(st.integers(0, 0xFFFF)), draw(st.integers(0, 255))) + draw(
            st.binary(max_size=32)
        )
    return draw(st.binary(max_size=32))


async def _serve(stream: bytes) -> tuple[UrController, _Writer]:
    ctl = UrController(ControllerVersion.parse("5.11"))
    emu = Emulator(ctl, "127.0.0.1", Ports())
    reader = asyncio.StreamReader()
    reader.feed_data(stream)
    reader.feed_eof()
    writer = _Writer()
    conn = RtdeConnection(emu, reader, writer)  # type: ignore[arg-type]
    await asyncio.wait_for(conn.run(), timeout=5.0)
    return ctl, writer


@settings(max_examples=250)
@given(st.lists(messages(), max_size=8))
def test_hostile_rtde_client_never_crashes_the_emulator(msgs: list[bytes]) -> None:
    ctl, writer = asyncio.run(_serve(b"".join(msgs)))
    assert writer.closed
    for _ in range(5):  # the controller still ticks and every value it streams is finite
        ctl.tick()
    assert np.all(np.isfinite(ctl.q))
    assert np.all(np.isfinite(ctl.tcp))


def test_reply_to_protocol_version_request() -> None:
    _, writer = asyncio.run(_serve(proto.pack(proto.REQUEST_PROTOCOL_VERSION, b"\x00\x02")))
    assert bytes(writer.sent) == proto.pack(proto.REQUEST_PROTOCOL_VERSION, b"\x01")


def test_short_header_closes_the_connection_quietly(capsys: Any) -> None:
    _, writer = asyncio.run(_serve(proto.HEADER.pack(2, proto.TEXT_MESSAGE)))
    assert writer.closed
    assert "size 2 < 3" in capsys.readouterr().err
