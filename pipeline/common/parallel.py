"""Mapping a job's independent pieces of work (a scene's candidates, a dataset's images)
over dask: in this process on threads, on an existing ``dask.distributed`` cluster, or
serially in the calling thread.

:func:`work_mapper` yields a :class:`Mapper`; ``mapper.map(fn, items, shared)`` calls
``fn(shared, item)`` for every item and returns the results in the items' order, so the
order in which the work is done never shows in the output (the seeds are drawn per
scene and candidate, never from a shared stream). ``fn`` must be a module-level
function and ``shared`` picklable (with cloudpickle) for a cluster of processes.

State that must not be shared between threads (an EGL renderer is bound to the thread
that made it current; a loader that caches the last image is not thread-safe) goes into
:class:`PerThread`: each thread gets its own, made on first use, and the mapper closes
them in the threads that made them when the map ends.

Which mapper:

- an address (``--config dask_scheduler=tcp://host:8786``, else the environment
  variable ``DASK_SCHEDULER_ADDRESS``): a ``distributed.Client`` connected to it within
  :data:`CONNECT_TIMEOUT_S`, else :class:`SchedulerUnreachable` (one line naming the
  address and the option);
- else ``threads`` > 1: dask's threaded scheduler on a pool of that many threads, owned
  by the mapper (so that the per-thread state can be closed in its threads);
- else: a plain loop in the calling thread (no dask import at all: importing
  ``distributed`` costs 1.5-4 s here).
"""

from __future__ import annotations

import logging
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, Callable, Generic, Iterator, Sequence, TypeVar

from pipeline.common.config import ManifestError

SCHEDULER_ENV = "DASK_SCHEDULER_ADDRESS"
"""Environment variable naming a dask scheduler when the run manifest does not."""
CONNECT_TIMEOUT_S = 5.0
"""How long to try to reach a dask scheduler before failing (s), per attempt: a TCP
connection first (no dask import: a closed port fails at once), then the client's
handshake; with the 1.5-4 s import of ``distributed`` between them the whole stays
under 10 s on a loaded 2-core machine."""

T = TypeVar("T")
R = TypeVar("R")
S = TypeVar("S")


class SchedulerUnreachable(ManifestError):
    """The dask scheduler the run names could not be reached. A :class:`ManifestError`
    (the option's value is unusable), so commands print its one line and exit 1."""


class SchedulerLost(SchedulerUnreachable):
    """The dask scheduler (or the connection to it) went away while a job's tasks ran on
    it: the job fails with one line naming the scheduler and how to resume, instead of a
    ``FutureCancelledError`` traceback per task."""

    def __init__(self, address: str, why: str):
        super().__init__(
            f"lost the dask scheduler at {address} while this job's tasks ran on it ({why}): start the scheduler "
            f"and its workers again (or unset the run option dask_scheduler and ${SCHEDULER_ENV} to work in this "
            "process), then run the same command again (freeze run ...) to resume: the items already published "
            "are kept")
        self.address = address


def scheduler_address(option: str | None) -> str | None:
    """The dask scheduler to use: the run's ``dask_scheduler`` option, else
    ``$DASK_SCHEDULER_ADDRESS``, else None (work in this process)."""
    address = (option or os.environ.get(SCHEDULER_ENV) or "").strip()
    return address or None


class PerThread(Generic[T]):
    """One object per thread, made by ``factory()`` on first use in that thread.

    Picklable: a copy (sent to a cluster's worker) keeps the factory only and makes its
    own objects there. :meth:`close_mine` closes (``close()`` or ``__exit__``) the
    calling thread's object; the mapper calls it in every thread that worked.
    """

    def __init__(self, factory: Callable[[], T]):
        self.factory = factory
        self._local = threading.local()

    def get(self) -> T:
        """The calling thread's object."""
        obj = getattr(self._local, "obj", None)
        if obj is None:
            obj = self._local.obj = self.factory()
        return obj

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        """Call the calling thread's object (for callables such as a verifier)."""
        return self.get()(*args, **kwargs)

    def close_mine(self) -> None:
        """Close the calling thread's object, if it made one. Errors are swallowed:
        pyrender terminates the EGL display shared by the process when one of its
        renderers is deleted, so a second renderer's teardown can find its context gone
        (its memory goes with the process)."""
        obj = getattr(self._local, "obj", None)
        self._local.obj = None
        if obj is None:
            return
        try:
            if hasattr(obj, "close"):
                obj.close()
            elif hasattr(obj, "__exit__"):
                obj.__exit__(None, None, None)
        except Exception:  # noqa: BLE001 - see the docstring
            pass

    def __getstate__(self) -> dict[str, Any]:
        return {"factory": self.factory}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.factory = state["factory"]
        self._local = threading.local()


@dataclass(frozen=True)
class ThreadMethod:
    """``tools.get().<name>(*args)``: a method of the calling thread's object of a
    :class:`PerThread` (a verifier, a fine ICP), as one picklable callable: a copy sent
    to a cluster's worker calls that worker's own object."""

    tools: PerThread
    name: str

    def __call__(self, *args: Any) -> Any:
        return getattr(self.tools.get(), self.name)(*args)


class Mapper:
    """Calls ``fn(shared, item)`` for each item, serially in the calling thread.

    ``kind``: ``serial``, ``threads`` or ``cluster``; ``workers``: how many calls may run
    at once (1 serial; the threads; the cluster's worker threads)."""

    kind = "serial"

    def __init__(self) -> None:
        self.workers = 1
        self._per_thread: list[PerThread] = []

    def per_thread(self, factory: Callable[[], T]) -> PerThread[T]:
        """A :class:`PerThread` of ``factory``, closed in its threads when the mapper ends."""
        p = PerThread(factory)
        self._per_thread.append(p)
        return p

    def map(self, fn: Callable[[S, T], R], items: Sequence[T], shared: S,
            done: Callable[[], None] | None = None) -> list[R]:
        """``[fn(shared, item) for item in items]``; ``done()`` is called in the calling
        thread after each item (for a progress bar), in the order they finish."""
        out = []
        for item in items:
            out.append(fn(shared, item))
            if done is not None:
                done()
        return out

    def close(self) -> None:
        for p in self._per_thread:
            p.close_mine()


def _call(fn: Callable[[S, T], R], shared: S, item: T) -> R:
    return fn(shared, item)


class ThreadMapper(Mapper):
    """dask's threaded scheduler on a pool of ``threads`` threads owned by the mapper."""

    kind = "threads"

    def __init__(self, threads: int):
        super().__init__()
        self.workers = int(threads)
        self._pool = ThreadPoolExecutor(self.workers, thread_name_prefix="freeze-dask")

    def map(self, fn: Callable[[S, T], R], items: Sequence[T], shared: S,
            done: Callable[[], None] | None = None) -> list[R]:
        if len(items) <= 1:  # nothing to spread: no dask, no thread hop
            return super().map(fn, items, shared, done)
        from functools import partial

        from dask.callbacks import Callback
        from dask.threaded import get

        # Each task is a bare partial: dask would otherwise look into the arguments for
        # keys and tasks (a tuple that starts with a callable is a task to dask).
        dsk = {("item", i): (partial(_call, fn, shared, item),) for i, item in enumerate(items)}
        keys = list(dsk)
        posttask = (lambda *_: done()) if done is not None else None
        # dask calls posttask in the calling thread, as each result arrives.
        with Callback(posttask=posttask):
            return list(get(dsk, keys, pool=self._pool))

    def close(self) -> None:
        """Close the per-thread state in the threads that made it (EGL contexts are
        current in their thread), one thread at a time, then stop the pool."""
        if self._per_thread:
            barrier = threading.Barrier(self.workers)
            lock = threading.Lock()

            def close_here() -> None:
                # The barrier holds every pool thread until all have a task, so each of
                # the ``workers`` tasks runs in a different thread.
                barrier.wait(timeout=60)
                with lock:
                    for p in self._per_thread:
                        p.close_mine()

            for f in [self._pool.submit(close_here) for _ in range(self.workers)]:
                f.result()
        self._pool.shutdown(wait=True)
        super().close()  # anything the calling thread made itself


class _OneLineErrors(logging.Filter):
    """Folds the traceback of a log record into one line (``message (Type: first line)``).

    distributed's client logs each failed attempt to reach a scheduler that went away
    with its full traceback; the job then fails with :class:`SchedulerLost`, and those
    tracebacks in the job's log would hide its one line."""

    def filter(self, record: logging.LogRecord) -> bool:
        if record.exc_info and record.exc_info[1] is not None:
            e = record.exc_info[1]
            why = str(e).splitlines()[0] if str(e) else ""
            record.msg = f"{record.getMessage()} ({type(e).__name__}{': ' + why if why else ''})".replace("%", "%%")
            record.args = ()
            record.exc_info = None
            record.exc_text = None
        record.stack_info = None
        return True


def _distributed_handlers() -> list[logging.Handler]:
    """The handlers of distributed's loggers (it gives several of them their own, and
    they do not propagate)."""
    names = [n for n in logging.root.manager.loggerDict if n == "distributed" or n.startswith("distributed.")]
    return list({id(h): h for n in names for h in logging.getLogger(n).handlers}.values())


class ClusterMapper(Mapper):
    """A ``distributed.Client`` of an existing cluster: ``shared`` is scattered once per
    map, the items are submitted one task each, the results gathered as they finish."""

    kind = "cluster"

    def __init__(self, client: Any, address: str | None = None):
        super().__init__()
        self.client = client
        self.address = address or str(getattr(client.scheduler, "address", "") or "the scheduler")
        self.workers = max(1, sum(client.nthreads().values()))
        self._filter = _OneLineErrors()
        self._handlers = _distributed_handlers()
        for h in self._handlers:
            h.addFilter(self._filter)

    def map(self, fn: Callable[[S, T], R], items: Sequence[T], shared: S,
            done: Callable[[], None] | None = None) -> list[R]:
        from concurrent.futures import CancelledError

        from distributed import as_completed
        from distributed.comm.core import CommClosedError

        if not items:
            return []
        futures: list[Any] = []
        shared_f = None
        out: list[Any] = [None] * len(items)
        try:
            shared_f = self.client.scatter(shared, hash=False)
            futures = [self.client.submit(_call, fn, shared_f, item, pure=False) for item in items]
            index = {f.key: i for i, f in enumerate(futures)}
            for f in as_completed(futures, loop=self.client.loop):
                out[index[f.key]] = f.result()  # raises the task's own exception
                if done is not None:
                    done()
        except (CancelledError, CommClosedError) as e:
            # Our tasks are cancelled only when the scheduler forgets them (it went away,
            # or the connection to it did): a task's own error arrives as itself. (The
            # task's own CommClosedError, if it opened connections of its own, reads the
            # same; none of the stages' tasks does.)
            raise SchedulerLost(self.address, f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else 'no reason'}"
                                ) from None
        finally:
            try:
                self.client.cancel([*futures, *([shared_f] if shared_f is not None else [])])
            except (CancelledError, OSError):  # a scheduler that went away has nothing left to cancel
                pass
        return out

    def close(self) -> None:
        # The workers' per-thread state goes with the scattered object; the client only.
        try:
            self.client.close()
        finally:
            for h in self._handlers:
                h.removeFilter(self._filter)


def connect(address: str, timeout: float = CONNECT_TIMEOUT_S) -> Any:
    """A ``distributed.Client`` of the scheduler at ``address``, once it has a worker;
    raises :class:`SchedulerUnreachable` when it cannot be reached or has no worker
    within ``timeout`` seconds."""
    import socket
    from urllib.parse import urlsplit

    try:
        url = urlsplit(address if "://" in address else f"tcp://{address}")
        if url.scheme in ("tcp", "tls") and url.hostname:
            socket.create_connection((url.hostname, url.port or 8786), timeout=timeout).close()
        from distributed import Client

        client = Client(address, timeout=timeout, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as e:
        why = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise SchedulerUnreachable(
            f"cannot reach the dask scheduler at {address} ({why}; waited at most {timeout:g} s): start it, or "
            f"unset the run option dask_scheduler (--config dask_scheduler=...) and ${SCHEDULER_ENV} to work in "
            "this process") from None
    try:
        # A scheduler without workers would take the tasks and never run them.
        client.wait_for_workers(1, timeout=timeout)
    except (OSError, TimeoutError) as e:
        client.close()
        raise SchedulerUnreachable(
            f"the dask scheduler at {address} has no worker (none joined within {timeout:g} s): start workers "
            f"(dask worker {address}), or unset the run option dask_scheduler and ${SCHEDULER_ENV}") from e
    return client


@contextmanager
def work_mapper(scheduler: str | None = None, threads: int | None = None) -> Iterator[Mapper]:
    """The mapper of a job (see the module docstring): on the cluster at ``scheduler``
    (an address, or None: see :func:`scheduler_address`, which the caller applies), else
    on ``threads`` threads (None or 1: serially in this thread)."""
    if scheduler:
        mapper: Mapper = ClusterMapper(connect(scheduler), scheduler)
    elif threads is not None and threads > 1:
        mapper = ThreadMapper(threads)
    else:
        mapper = Mapper()
    try:
        yield mapper
    finally:
        mapper.close()


def job_mapper(scheduler_option: str | None, threads_help: bool) -> Any:
    """The mapper of a stage job: on the cluster the run names (``dask_scheduler``, else
    ``$DASK_SCHEDULER_ADDRESS``), else on the job's threads (:func:`pipeline.common.threads.job_threads`,
    or every CPU outside a job) when ``threads_help`` (the stage's work was measured to
    run faster on threads, ``benchmarks/results/dask.md``), else serially. A context
    manager, as :func:`work_mapper`."""
    from pipeline.common.threads import job_threads

    threads = (job_threads() or os.cpu_count() or 1) if threads_help else 1
    return work_mapper(scheduler_address(scheduler_option), threads)
