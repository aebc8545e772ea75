"""Run independent per-scene tasks inline, on a local process pool, or as Ray tasks.

Every executor yields results as tasks finish (in completion order) and forwards progress
messages ``(key, done, total)`` that tasks send through the ``progress`` handle they receive.
Stopping early (the consumer closes the iterator, or an interrupt or error escapes it) cancels the
tasks not yet started and stops the running ones: when the iterator is closed, no worker process
still runs. Pool workers ignore Ctrl-C; the coordinating process decides what an interrupt stops.
"""

from __future__ import annotations

import multiprocessing as mp
import queue as queue_module
import signal
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from typing import Any, Literal, Protocol, TypeVar

ExecutorName = Literal["local", "ray"]
EXECUTORS: tuple[ExecutorName, ...] = ("local", "ray")

T = TypeVar("T")
R = TypeVar("R")
ProgressMessage = tuple[str, int, int, str]


class ProgressHandle(Protocol):
    def put(self, item: ProgressMessage) -> None: ...


class _CallbackHandle:
    """A progress handle for inline execution: calls the callback directly."""

    def __init__(self, callback: Callable[[ProgressMessage], None]):
        self.callback = callback

    def put(self, item: ProgressMessage) -> None:
        self.callback(item)


def run_tasks(
    fn: Callable[[T, ProgressHandle | None], R],
    tasks: Sequence[T],
    executor: ExecutorName = "local",
    workers: int = 1,
    ray_address: str | None = None,
    on_progress: Callable[[ProgressMessage], None] | None = None,
) -> Iterator[R]:
    """Runs ``fn(task, progress)`` for every task and yields the results as they complete.

    ``local`` with ``workers <= 1`` runs inline in this process; with more workers it uses a
    process pool (spawned processes, so native libraries start clean). ``ray`` submits Ray tasks
    to the cluster at ``ray_address`` (or a local Ray started with ``workers`` CPUs).
    A consumer that stops early (closing the iterator) cancels the tasks not yet started and stops
    the running ones.
    """
    if executor == "local":
        if workers <= 1:
            handle = _CallbackHandle(on_progress) if on_progress else None
            for task in tasks:
                yield fn(task, handle)
            return
        yield from _run_pool(fn, tasks, workers, on_progress)
    elif executor == "ray":
        yield from _run_ray(fn, tasks, workers, ray_address, on_progress)
    else:
        raise ValueError(f"unknown executor {executor!r}; choose one of {EXECUTORS}")


def _drain(q: Any, on_progress: Callable[[ProgressMessage], None] | None) -> None:
    while True:
        try:
            item = q.get_nowait()
        except (queue_module.Empty, Exception):
            return
        if on_progress is not None:
            on_progress(item)


def _ignore_interrupts() -> None:
    """Pool worker initializer: Ctrl-C reaches the whole process group, and only the coordinator
    should act on it (it stops the workers itself)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _run_pool(
    fn: Callable[[T, ProgressHandle | None], R],
    tasks: Sequence[T],
    workers: int,
    on_progress: Callable[[ProgressMessage], None] | None,
) -> Iterator[R]:
    ctx = mp.get_context("spawn")
    with ctx.Manager() as manager:
        q = manager.Queue()
        pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_ignore_interrupts)
        finished = False
        try:
            pending: set[Future[R]] = {pool.submit(fn, task, q) for task in tasks}
            while pending:
                done, pending = wait(pending, timeout=0.2, return_when=FIRST_COMPLETED)
                _drain(q, on_progress)
                for fut in done:
                    yield fut.result()
            _drain(q, on_progress)
            finished = True
        finally:
            if finished:
                pool.shutdown(wait=True)
            else:
                _stop_pool(pool)


#: How long a worker process gets to exit after SIGTERM before it is killed, in seconds.
_WORKER_EXIT_WAIT_S = 10.0


def _stop_pool(pool: ProcessPoolExecutor) -> None:
    """Stops a pool now: cancels the tasks not started, terminates the worker processes (running
    tasks included) and waits until they have exited, so no worker writes after this returns."""
    # ProcessPoolExecutor has no public way to stop running tasks before Python 3.14's
    # terminate_workers(); its process table is the one handle on them.
    processes = list((getattr(pool, "_processes", None) or {}).values())
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        process.terminate()
    for process in processes:
        process.join(_WORKER_EXIT_WAIT_S)
        if process.is_alive():
            process.kill()
            process.join()


def _run_ray(
    fn: Callable[[T, ProgressHandle | None], R],
    tasks: Sequence[T],
    workers: int,
    ray_address: str | None,
    on_progress: Callable[[ProgressMessage], None] | None,
) -> Iterator[R]:
    try:
        # optional dependency: only for --executor ray
        import ray
        from ray.util.queue import Queue
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise RuntimeError("--executor ray needs Ray: pip install 'phigenesis[ray]'") from e
    started_here = not ray.is_initialized()
    if started_here:
        if ray_address:
            ray.init(address=ray_address, log_to_driver=False)
        else:
            ray.init(num_cpus=max(1, workers), include_dashboard=False, log_to_driver=False)
    try:
        q = Queue()
        remote_fn = ray.remote(num_cpus=1, max_retries=0)(fn)
        refs = {remote_fn.remote(task, q): i for i, task in enumerate(tasks)}
        try:
            while refs:
                done, _ = ray.wait(list(refs), num_returns=1, timeout=0.2)
                _drain(q, on_progress)
                for ref in done:
                    refs.pop(ref)
                    yield ray.get(ref)
            _drain(q, on_progress)
        finally:
            for ref in refs:  # stopped early: end the running tasks too, not only the queued ones
                ray.cancel(ref, force=True)
    finally:
        if started_here:
            ray.shutdown()
