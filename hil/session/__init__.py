"""Session log: tamper-evident JSON lines of everything a procedure did."""

from hil.session.log import (
    GENESIS_SHA256,
    SessionLog,
    SessionLogError,
    VerifyReport,
    file_sha256,
    read_session_log,
    verify_session_log,
)

__all__ = [
    "GENESIS_SHA256",
    "SessionLog",
    "SessionLogError",
    "VerifyReport",
    "file_sha256",
    "read_session_log",
    "verify_session_log",
]
