"""Where an evaluation's independent tasks run: worker processes here, or a Ray cluster.

An evaluation (``eval nav``'s trials) is many independent calls ``function(shared, item)``:
``shared`` the same for all (the config), ``item`` one task's own (a trial). An executor runs
them and yields each result as it completes, with the item's index.

- :class:`LocalPool`, the default, needs nothing installed: ``spawn`` worker processes on this
  machine (each starts clean, with its own OpenGL context), ``workers`` of them. A worker
  ends itself within a second of its parent's death: a run stopped by ``kill`` (SIGTERM or
  SIGKILL, which run no clean-up) once left its workers flying trials nobody would read, for
  over an hour.
- :class:`RayCluster` runs each call as a task on an existing Ray cluster (``--cluster auto``
  for the cluster this machine's ``ray start`` joined, ``HOST:PORT`` for the head's address
  as ``ray start --head`` prints it, or ``ray://HOST:PORT`` through Ray Client; the ``ray``
  package is the extra ``companion[cluster]``). Ray places each task where
  a CPU is free (``num_cpus=1``), keeps ``shared`` once in its object store for every task,
  and runs a task again when its worker process or node dies (``max_retries``): a node lost
  mid-run loses nothing. A task that raises is not retried (the evaluation records its own
  errors); an exception that escapes it ends the run.

Every node must run the same code on the same libraries as the machine that started the run,
since each record is stamped with this machine's revision and library versions: each task
checks its node's (:func:`~companion.tools.eval.provenance.code_revision`,
:func:`~companion.tools.eval.provenance.library_versions`) and refuses to run otherwise.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import importlib
import logging
import multiprocessing
import os
import socket
import sys
import threading
import time
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable, Iterator, Sequence

from companion.tools.eval import provenance
from companion.tools.eval.vio import EvaluationError

#: Times Ray runs a task again after its worker or node died.
RAY_RETRIES = 3
#: Seconds to wait for a cluster's address to answer before saying it cannot be reached.
CONNECT_TIMEOUT_S = 5.0
#: How often a local worker checks that the process that started it is alive, seconds.
PARENT_CHECK_S = 0.5


class ExecutorError(EvaluationError):
    """The executor cannot run the tasks: a worker pool that died, a cluster that cannot be
    reached or is not installed, a node with other code."""


def open_executor(cluster: str | None, workers: int | None, tasks: int):
    """:class:`RayCluster` at ``cluster`` (``auto``, ``HOST:PORT`` or ``ray://HOST:PORT``) or,
    without one, a :class:`LocalPool` of ``workers`` processes (default: the CPU count), never
    more than ``tasks``."""
    if workers is not None and workers < 1:
        raise ExecutorError(f"workers must be at least 1, got {workers}")
    if cluster:
        if workers is not None:
            raise ExecutorError("--workers sizes the local pool; a cluster runs a task on "
                                "every free CPU")
        return RayCluster(cluster)
    return LocalPool(min(workers or os.cpu_count() or 1, max(tasks, 1)))


def _log_errors_only(level: int) -> None:
    """A worker's logging: errors only, on stderr, so that a task's warnings do not bury the
    progress bar (its record keeps what matters)."""
    logging.basicConfig(level=max(level, logging.ERROR), stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(processName)s %(name)s: "
                               "%(message)s")


def _start_worker(level: int, parent: int) -> None:
    """A local worker's set-up: its logging (:func:`_log_errors_only`), and a daemon thread
    that ends the process once ``parent``, the run's process, is gone (module docstring)."""
    _log_errors_only(level)
    threading.Thread(target=_exit_with_parent, args=(parent,), daemon=True,
                     name="parent-watch").start()


def _exit_with_parent(parent: int) -> None:
    """Poll every :data:`PARENT_CHECK_S` whether this process's parent is still ``parent``
    (an orphan is adopted by another), and end the process at once when it is not."""
    while os.getppid() == parent:
        time.sleep(PARENT_CHECK_S)
    os._exit(1)


class LocalPool:
    """``workers`` ``spawn`` processes on this machine."""

    def __init__(self, workers: int):
        self.workers = workers
        self.where = f"{workers} worker process{'es' if workers > 1 else ''}"

    def run(self, function: Callable, shared: Any,
            items: Sequence) -> Iterator[tuple[int, Any]]:
        """``(index, function(shared, items[index]))`` for every item, as each completes."""
        pool = concurrent.futures.ProcessPoolExecutor(
            self.workers, mp_context=multiprocessing.get_context("spawn"),
            initializer=_start_worker,
            initargs=(logging.getLogger().getEffectiveLevel(), os.getpid()))
        try:
            futures = {pool.submit(function, shared, item): k for k, item in enumerate(items)}
            for future in concurrent.futures.as_completed(futures):
                yield futures[future], future.result()
        except BrokenProcessPool:
            raise ExecutorError("a worker process died (out of memory?); no result") from None
        finally:
            pool.shutdown(wait=True, cancel_futures=True)


class RayCluster:
    """Tasks on the Ray cluster at ``address`` (module docstring)."""

    def __init__(self, address: str):
        self.ray = _ray()
        self.address = address
        _check_reachable(address)
        try:
            self.ray.init(address=address, logging_level=logging.ERROR,
                          log_to_driver=False, configure_logging=False)
        except (ConnectionError, RuntimeError, ValueError) as error:
            raise ExecutorError(f"cannot reach the Ray cluster at {address}: {error}") from None
        self.workers = max(1, int(self.ray.cluster_resources().get("CPU", 1)))
        self.where = f"the Ray cluster at {address} ({self.workers} CPUs)"

    def run(self, function: Callable, shared: Any,
            items: Sequence) -> Iterator[tuple[int, Any]]:
        """``(index, function(shared, items[index]))`` for every item, as each completes."""
        ray = self.ray
        task = ray.remote(num_cpus=1, max_retries=RAY_RETRIES,
                          retry_exceptions=False)(_checked_call)
        # Ray prints what its nodes report (a raylet that died) on the driver's stdout, which
        # carries the evaluation's report: while Ray runs, stdout is stderr.
        with contextlib.redirect_stdout(sys.stderr):
            shared_ref = ray.put(shared)
            made_by = (provenance.code_revision(), provenance.library_versions())
            pending = {task.remote(function, shared_ref, item, made_by): k
                       for k, item in enumerate(items)}
            try:
                while pending:
                    done, _ = ray.wait(list(pending), num_returns=1)
                    yield pending.pop(done[0]), self._result(done[0])
            finally:
                for ref in pending:
                    ray.cancel(ref, force=True)
                ray.shutdown()

    def _result(self, ref):
        try:
            return self.ray.get(ref)
        except self.ray.exceptions.RayTaskError as error:
            cause = error.cause if isinstance(error.cause, ExecutorError) else error
            raise ExecutorError(f"a task failed on the cluster: {cause}") from None
        except self.ray.exceptions.RayError as error:
            raise ExecutorError(f"a task was lost on the cluster after {RAY_RETRIES} retries: "
                                f"{type(error).__name__}: {error}") from None


def _check_reachable(address: str) -> None:
    """ExecutorError at once unless something listens at ``address`` (``HOST:PORT`` or
    ``ray://HOST:PORT``; ``auto`` is Ray's own to find): ``ray.init`` retries an unreachable
    address for minutes."""
    if address == "auto":
        return
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        raise ExecutorError(f"a Ray cluster address is auto, HOST:PORT or ray://HOST:PORT, "
                            f"got {address!r}")
    try:
        socket.create_connection((host, int(port)), timeout=CONNECT_TIMEOUT_S).close()
    except OSError as error:
        raise ExecutorError(f"cannot reach the Ray cluster at {address}: "
                            f"{error.strerror or error}") from None


def _checked_call(function: Callable, shared: Any, item: Any, made_by: tuple[str, str]) -> Any:
    """``function(shared, item)`` on a node, after checking that the node runs the driver's
    ``made_by``: its code revision and library versions (:mod:`provenance`)."""
    revision, libraries = made_by
    here = provenance.code_revision()
    if here != revision:
        raise ExecutorError(f"node {os.uname().nodename} runs revision {here}, the run "
                            f"{revision}: install the same code on every node")
    installed = provenance.library_versions()
    if installed != libraries:
        raise ExecutorError(f"node {os.uname().nodename} has {installed}, the run {libraries}: "
                            "install the same versions on every node (its flights would differ)")
    _log_errors_only(logging.ERROR)
    return function(shared, item)


def _ray():
    try:
        return importlib.import_module("ray")
    except ImportError:
        raise ExecutorError("--cluster needs Ray: pip install 'companion[cluster]'") from None
