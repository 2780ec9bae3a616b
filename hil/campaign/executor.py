"""Where a campaign's runs execute: ``local`` (threads of this process, each driving one run's
child process, ``--jobs`` at a time - the process pool as before) or ``dask`` (each run submitted
to a ``distributed.Client``: the scheduler at ``--scheduler``, or a LocalCluster on loopback).

Both run the same task function (:func:`hil.campaign.task.execute_task`) and share one retry
rule: a run whose process died, that hung past its bound, or whose Dask worker was lost is run
once more; if that fails too, its record says so (outcome ``hang`` or ``crashed``,
``attempts`` 2). Each run gives exactly one record, in the order of the tasks.
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import socket
import uuid
from abc import ABC, abstractmethod
from collections.abc import Callable
from types import TracebackType
from typing import Any

from hil.errors import HilError

from .runner import following_note
from .task import RunTask, TaskOutcome, _error_record, execute_task, finish_record, kill_running

Progress = Callable[[str], None]
#: Attempts of one run: the first, and one retry.
MAX_ATTEMPTS = 2
#: How long connecting to a ``--scheduler`` may take before it is an error (s).
SCHEDULER_CONNECT_TIMEOUT_S = 15.0
#: The extra that brings the Dask executor.
DASK_EXTRA = "campaign-dask"
#: How often the wait for finished runs wakes up to check the client (s).
_POLL_S = 2.0


class ExecutorError(HilError, RuntimeError):
    """The executor cannot be used: ``distributed`` not installed, the scheduler unreachable."""


def progress_line(rec: dict[str, Any]) -> str:
    """The progress line of a finished run (as the local pool has always printed it)."""
    lat = rec.get("safe_latency_ms")
    line = (f"{rec['run_id']}: {'pass' if rec['passed'] else 'FAIL'} {rec.get('outcome', '')}"
            + (f" {lat:.0f} ms" if isinstance(lat, int | float) else "")
            + following_note(rec)
            + ("" if rec["passed"] else f" ({'; '.join(rec.get('reasons', []))})"))
    return line + (f" [attempt {rec['attempts']}]" if rec.get("attempts", 1) > 1 else "")


class Executor(ABC):
    """Runs tasks; a context manager (entering starts or connects, leaving shuts everything down)."""

    #: ``{"kind": ..., ...}`` for the summary.
    description: dict[str, Any]

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, et: type[BaseException] | None, ev: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()

    @abstractmethod
    def close(self) -> None:
        """Release the workers (idempotent)."""

    @abstractmethod
    def _submit(self, task: RunTask, attempt: int) -> Any:
        """Start ``task``; return a future (``result()``, ``exception()``)."""

    @abstractmethod
    def _wait_any(self, futures: list[Any]) -> list[Any]:
        """Block until at least one of ``futures`` is done (or a poll interval passed); the done ones."""

    def _lost(self, task: RunTask, exc: BaseException) -> TaskOutcome:
        """The outcome of a task whose future failed (its worker died, the cluster went away)."""
        reason = f"worker lost: {type(exc).__name__}: {exc}".strip()
        rec = finish_record(task, _error_record(task, "crashed", [reason[:500]]))
        return TaskOutcome(rec, retryable=True)

    def run(self, tasks: list[RunTask], *, progress: Progress | None = None,
            on_files: Callable[[dict[str, bytes]], None] | None = None) -> list[dict[str, Any]]:
        """Run ``tasks``; return one record per task, in their order. ``on_files`` receives the log
        files a finished run sent back. Blocking."""
        say = progress or (lambda _m: None)
        pending: dict[Any, tuple[int, RunTask, int]] = {}
        for i, t in enumerate(tasks):
            pending[self._submit(t, 1)] = (i, t, 1)
        records: dict[int, dict[str, Any]] = {}
        while pending:
            for fut in self._wait_any(list(pending)):
                i, t, attempt = pending.pop(fut)
                try:
                    exc = fut.exception()
                except BaseException as cancelled:  # noqa: BLE001 - a cancelled future: its worker is gone
                    exc = cancelled
                out = self._lost(t, exc) if exc is not None else fut.result()
                if out.retryable and attempt < MAX_ATTEMPTS:
                    say(f"{t.run_id}: {out.record['outcome']} on attempt {attempt} "
                        f"({'; '.join(out.record['reasons'])}); running it once more")
                    pending[self._submit(t, attempt + 1)] = (i, t, attempt + 1)
                    continue
                rec = out.record
                rec["attempts"] = attempt
                if out.retryable:
                    rec["reasons"] = [f"after {attempt} attempts: {r}" for r in rec["reasons"]]
                records[i] = rec
                if on_files is not None and out.files:
                    on_files(out.files)
                say(progress_line(rec))
        return [records[i] for i in range(len(tasks))]


class LocalExecutor(Executor):
    """``jobs`` runs at a time on this machine (a thread per running run; each run is a child
    process)."""

    def __init__(self, jobs: int) -> None:
        if jobs < 1:
            raise ValueError(f"jobs must be >= 1, got {jobs}")
        self.jobs = jobs
        self.description = {"kind": "local", "workers": jobs}
        self._pool = cf.ThreadPoolExecutor(max_workers=jobs, thread_name_prefix="campaign-run")

    def close(self) -> None:
        """Cancel the runs not started, kill the running ones (an interrupted campaign: a finished
        one has none), wait for the threads."""
        self._pool.shutdown(wait=False, cancel_futures=True)
        kill_running()
        self._pool.shutdown(wait=True)

    def _submit(self, task: RunTask, attempt: int) -> Any:
        return self._pool.submit(execute_task, task)

    def _wait_any(self, futures: list[Any]) -> list[Any]:
        return list(cf.wait(futures, timeout=_POLL_S, return_when=cf.FIRST_COMPLETED).done)


def _import_distributed() -> Any:
    try:
        import distributed
    except ImportError as exc:
        raise ExecutorError(
            f"--executor dask needs the '{DASK_EXTRA}' extra (Dask's distributed): "
            f"pip install 'needle-guide-hil[{DASK_EXTRA}]' ({exc})") from exc
    return distributed


def _probe_scheduler(scheduler: str, timeout_s: float) -> None:
    """A plain TCP connection to ``scheduler`` (``tcp://host:port`` or ``host:port``) within
    ``timeout_s``, before any Dask client exists: an unreachable address is a one-line error
    in bounded time, and no client (with its event-loop thread) is left half-started.

    Raises:
        ExecutorError: the address is malformed or nothing accepts a connection there.
    """
    address = scheduler.split("://", 1)[1] if "://" in scheduler else scheduler
    host, sep, port_text = address.rpartition(":")
    if not sep or not host or not port_text.isdigit():
        raise ExecutorError(f"--scheduler {scheduler}: expected tcp://HOST:PORT")
    try:
        with socket.create_connection((host.strip("[]"), int(port_text)), timeout=timeout_s):
            pass
    except OSError as exc:
        raise ExecutorError(f"--scheduler {scheduler}: no Dask scheduler answered within "
                            f"{timeout_s:g} s ({exc.strerror or type(exc).__name__})") from None


class DaskExecutor(Executor):
    """Each run submitted to a ``distributed.Client``: the scheduler at ``scheduler``
    (``tcp://host:port``), or a LocalCluster of ``workers`` single-threaded worker processes bound
    to 127.0.0.1 with no dashboard (its HTTP server on a free loopback port), started here and
    closed by :meth:`close`.

    A worker lost while running a task makes the scheduler fail the task at once on the
    LocalCluster (``allowed-failures`` 0); an external scheduler retries it itself
    ``distributed.scheduler.allowed-failures`` times first (docs/campaign.md).

    Raises:
        ExecutorError: ``distributed`` is not installed; no scheduler answered at ``scheduler``
            within ``connect_timeout_s`` (one line, naming the address).
    """

    def __init__(self, *, scheduler: str | None = None, workers: int = 2,
                 connect_timeout_s: float | None = None) -> None:
        if connect_timeout_s is None:
            connect_timeout_s = SCHEDULER_CONNECT_TIMEOUT_S
        distributed = _import_distributed()
        import dask

        self._distributed = distributed
        self._cluster: Any = None
        self._done: Any = None  # distributed.as_completed of every submitted future
        self._token = uuid.uuid4().hex[:12]
        if scheduler is not None:
            _probe_scheduler(scheduler, connect_timeout_s)
            with dask.config.set({"distributed.comm.timeouts.connect": f"{connect_timeout_s}s"}):
                try:
                    self._client = distributed.Client(scheduler, timeout=connect_timeout_s,
                                                      set_as_default=False)
                except (OSError, TimeoutError, ValueError) as exc:
                    detail = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                    raise ExecutorError(f"--scheduler {scheduler}: no Dask scheduler answered within "
                                        f"{connect_timeout_s:g} s ({detail})") from None
            n = len(self._client.scheduler_info().get("workers", {}))
            self.description = {"kind": "dask", "scheduler": scheduler, "workers": n}
            return
        with dask.config.set({"distributed.scheduler.allowed-failures": 0}):
            self._cluster = distributed.LocalCluster(
                n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                # the scheduler's HTTP server (health, metrics) always starts: on a free loopback
                # port, as None means 8787 (and a second campaign on the machine collided there)
                dashboard_address="127.0.0.1:0", scheduler_kwargs={"dashboard": False},
                silence_logs=logging.ERROR)
        try:
            self._client = distributed.Client(self._cluster, set_as_default=False)
        except BaseException:
            self._cluster.close()
            raise
        self.description = {"kind": "dask", "scheduler": "LocalCluster", "workers": workers}

    def close(self) -> None:
        client, self._client = getattr(self, "_client", None), None
        if client is not None:
            client.close()
        cluster, self._cluster = self._cluster, None
        if cluster is not None:
            cluster.close()

    def _submit(self, task: RunTask, attempt: int) -> Any:
        assert self._client is not None
        key = f"hil-campaign-{self._token}-{task.run_id}-a{attempt}"
        fut = self._client.submit(execute_task, task, key=key, retries=0)
        if self._done is None:
            self._done = self._distributed.as_completed(loop=self._client.loop)
        self._done.add(fut)
        return fut

    def _wait_any(self, futures: list[Any]) -> list[Any]:
        assert self._done is not None
        return list(self._done.next_batch(block=True))


def open_executor(kind: str, *, jobs: int, scheduler: str | None = None) -> Executor:
    """The executor ``--executor kind`` names (``local`` or ``dask``).

    Raises:
        ExecutorError: see :class:`DaskExecutor`; ``--scheduler`` with the local executor.
    """
    if kind == "local":
        if scheduler is not None:
            raise ExecutorError("--scheduler applies to --executor dask only")
        return LocalExecutor(jobs)
    if kind == "dask":
        return DaskExecutor(scheduler=scheduler, workers=jobs)
    raise ExecutorError(f"--executor {kind!r}: choose local or dask")
