"""``--shard I/N``: a deterministic slice of a campaign's matrix, for array jobs (Slurm job arrays,
Kubernetes Indexed Jobs), and the matrix's identity that ``hil campaign merge`` checks.

Shards are **0-based**: ``I`` runs from 0 to N-1 (``$SLURM_ARRAY_TASK_ID`` with ``--array=0-<N-1>``,
``$JOB_COMPLETION_INDEX`` of an Indexed Job). Shard I owns the matrix items at positions k with
``k % N == I`` (the matrix in its fixed order: per seed, the baseline then every scenario), so the
N shards partition the matrix, each item in exactly one, and every shard gets a mix of kinds.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from hil.errors import HilError

_SPEC = re.compile(r"(\d+)/(\d+)")


class ShardSpecError(HilError, ValueError):
    """A ``--shard`` value that is not ``I/N`` with 0 <= I < N."""


@dataclass(frozen=True)
class Shard:
    """Slice ``index`` (0-based) of ``count``."""

    index: int
    count: int

    def owns(self, position: int) -> bool:
        """Whether the matrix item at ``position`` (0-based) belongs to this shard."""
        return position % self.count == self.index

    def to_dict(self) -> dict[str, int]:
        return {"index": self.index, "count": self.count}

    def __str__(self) -> str:
        return f"{self.index}/{self.count}"


def parse_shard(text: str) -> Shard:
    """Parse ``I/N`` (0-based: ``0/4`` .. ``3/4``).

    Raises:
        ShardSpecError: not two integers ``I/N``, N < 1, or I >= N (one line, naming the option).
    """
    m = _SPEC.fullmatch(text.strip())
    if m is None:
        raise ShardSpecError(f"--shard {text!r}: expected I/N with 0 <= I < N (0-based), e.g. 0/4")
    index, count = int(m.group(1)), int(m.group(2))
    if count < 1:
        raise ShardSpecError(f"--shard {text!r}: the shard count N must be >= 1")
    if index >= count:
        raise ShardSpecError(f"--shard {text!r}: the shard index is 0-based, so it must be 0..{count - 1}")
    return Shard(index, count)


def matrix_identity(run_ids: Sequence[str]) -> dict[str, Any]:
    """``{"runs": len, "sha256": ...}`` of the whole (unsharded) matrix's run ids, in order: two
    shard outputs with the same identity are slices of the same matrix."""
    return {"runs": len(run_ids), "sha256": hashlib.sha256("\n".join(run_ids).encode()).hexdigest()}
