"""``[igtl]`` setup table: the optional OpenIGTLink server (3D Slicer / SlicerIGT)."""

from __future__ import annotations

import ipaddress

from pydantic import BaseModel, ConfigDict, Field, field_validator


class IgtlConfig(BaseModel):
    """OpenIGTLink streaming. Off by default; binds the loopback address unless ``host`` names
    another local IPv4 address (``0.0.0.0``: every interface — only on a trusted network).

    Attributes:
        enabled: start the server with the session.
        host: IPv4 address to bind.
        port: TCP port (18944 is the OpenIGTLink default; 0 picks a free port).
        rate_hz: maximum rate of the TRANSFORM stream (controller clock).
        status_rate_hz: maximum rate of the STRING/POINT status messages.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = Field(18944, ge=0, le=65535)
    rate_hz: float = Field(20.0, gt=0, le=200.0)
    status_rate_hz: float = Field(2.0, gt=0, le=50.0)

    @field_validator("host")
    @classmethod
    def _ipv4(cls, v: str) -> str:
        try:
            ipaddress.IPv4Address(v)
        except ValueError:
            raise ValueError(f"{v!r} is not an IPv4 address (e.g. 127.0.0.1)") from None
        return v
