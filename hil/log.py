"""structlog configuration: human-readable on a terminal, JSON lines when asked.

Event names are ``snake_case`` facts (``transition_applied``, ``fault_injected``); the data goes
in fields, never in formatted strings. Logs go to stderr so that commands can print JSON results
on stdout.
"""

from __future__ import annotations

import logging
import sys
from typing import Any, TextIO

import structlog

_LEVELS = {"debug": logging.DEBUG, "info": logging.INFO, "warning": logging.WARNING,
           "error": logging.ERROR}


def configure_logging(*, json: bool = False, level: str = "info", stream: TextIO | None = None) -> None:
    """Configure structlog once for the process.

    Args:
        json: emit one JSON object per line instead of the coloured console renderer.
        level: minimum level, one of debug, info, warning, error.
        stream: where to write (default: stderr).

    Raises:
        ValueError: unknown level.
    """
    if level not in _LEVELS:
        raise ValueError(f"unknown log level {level!r}; use one of {sorted(_LEVELS)}")
    out: Any = stream if stream is not None else _CurrentStderr()
    processors: list[Any] = [
        structlog.contextvars.merge_contextvars,
        structlog.processors.add_log_level,
        structlog.processors.TimeStamper(fmt="iso", utc=True),
    ]
    if json:
        processors += [structlog.processors.dict_tracebacks, structlog.processors.JSONRenderer()]
    else:
        processors.append(structlog.dev.ConsoleRenderer(colors=out.isatty()))
    structlog.configure(
        processors=processors,
        wrapper_class=structlog.make_filtering_bound_logger(_LEVELS[level]),
        logger_factory=structlog.PrintLoggerFactory(file=out),
        cache_logger_on_first_use=False,
    )


def get_logger(name: str) -> Any:
    """A structlog logger bound with ``logger=name``."""
    # Lazy: a module-level logger created before configure_logging() still follows the
    # configuration made later (structlog's bind() would resolve it at import time).
    return _LazyLogger(name)


class _LazyLogger:
    """Resolves ``structlog.get_logger().bind(logger=name)`` at each use."""

    def __init__(self, name: str) -> None:
        self._name = name

    def __getattr__(self, item: str) -> Any:
        return getattr(structlog.get_logger().bind(logger=self._name), item)


class _CurrentStderr:
    """Writes to whatever ``sys.stderr`` is at the time of writing (not at configuration), so a
    replaced stderr (pytest capture, a closed pipe) does not leave a dangling logger behind."""

    def write(self, text: str) -> int:
        return sys.stderr.write(text)

    def flush(self) -> None:
        sys.stderr.flush()

    def isatty(self) -> bool:
        return sys.stderr.isatty()
