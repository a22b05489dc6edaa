"""The Dask engine shared by ``vet batch`` (captures) and tiled ``vet deblur`` (tiles).

:func:`dask_client` yields a :class:`distributed.Client` on an embedded
:class:`distributed.LocalCluster` on the loopback interface (``workers`` processes, one
thread each, no dashboard) or on an existing cluster's ``scheduler`` (``tcp://HOST:PORT``).
Worker processes are limited to one OpenMP/BLAS/OpenCV/OpenImageIO thread each
(:data:`WORKER_ENV`, :func:`limit_threads`), so N workers use N cores and no more.

Shutdown is quiet: Dask's worker heartbeats race the closing scheduler on a loaded
machine and log a traceback ("Failed to communicate with scheduler during heartbeat",
CommClosedError) although every result is in. The client is closed before the cluster
(workers, then scheduler), each within :data:`CLOSE_TIMEOUT_S`, with Dask's loggers
raised to CRITICAL in this process while they close, and an embedded cluster's workers
pass nothing below CRITICAL once they are closing (:func:`quiet_shutdown_plugin`). Errors
logged while the cluster works still show.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from typing import Any, TypeVar

from .errors import UsageError, VetError

T = TypeVar("T")

#: Environment for worker processes: one thread each for OpenMP, BLAS and OpenCV.
WORKER_ENV = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "NUMEXPR_NUM_THREADS": "1",
    "OPENCV_FOR_THREADS_NUM": "1",
}
#: Seconds to wait for an existing cluster's first worker.
CONNECT_TIMEOUT_S = 30.0
#: Seconds a scheduler has to accept a connection and answer vet's first question
#: (:func:`check_scheduler`): a few, so that a port where no Dask scheduler listens (a
#: silent listener, a web server) fails at once.
HANDSHAKE_TIMEOUT_S = 5.0
#: Address schemes vet connects to (Dask's ``inproc://`` lives in one process only).
SCHEDULER_SCHEMES = ("tcp",)
#: Seconds the client, then the embedded cluster, may take to close.
CLOSE_TIMEOUT_S = 30.0
#: Loggers whose records Dask's shutdown races produce.
SHUTDOWN_LOGGERS = ("distributed", "tornado", "asyncio")

_threads_limited = False
#: Whether this process was started with ``OMP_NUM_THREADS=1`` (by whoever started it),
#: read once: Dask's nanny sets that variable in the process that starts its workers
#: (``distributed.nanny.pre-spawn-environ``, "even if this means poisoning the process
#: running the Nanny"), which must not make that process's own work single-threaded.
_started_one_thread = os.environ.get("OMP_NUM_THREADS") == "1"
#: Per-thread state (:func:`one_thread_here`).
_local = threading.local()
#: Blocks of :func:`opencv_single_threaded` open at once, and the setting they restore.
_cv_lock = threading.Lock()
_cv_depth = 0
_cv_before = 1


#: The most threads a solve's products use in a process that is not limited.
MAX_SOLVE_THREADS = 4


def solve_threads() -> int:
    """Threads the deblur's products may use in this process: one in a limited worker
    (:func:`limit_threads`, or a process started with ``OMP_NUM_THREADS=1``) or on a
    thread inside :func:`one_thread_here`, else the cores, at most
    :data:`MAX_SOLVE_THREADS`. (The variable as the process started: a Dask cluster
    started here sets it for its workers' sake.)"""
    if _threads_limited or _started_one_thread or _local.__dict__.get("one"):
        return 1
    return max(1, min(MAX_SOLVE_THREADS, os.cpu_count() or 1))


@contextlib.contextmanager
def one_thread_here() -> Iterator[None]:
    """:func:`solve_threads` is 1 on the calling thread inside the block: for work that
    runs beside other such work on a pool that already shares the cores."""
    _local.one = True
    try:
        yield
    finally:
        _local.one = False


def in_order(
    fn: Callable[[int], T], n: int, ahead: int = 1, most: int | None = None
) -> Iterator[T]:
    """``fn(0), ..., fn(n - 1)``, handed out in that order, computed on
    :func:`solve_threads` threads (at most ``most``) with at most ``ahead`` calls per
    thread running or done beyond the one handed out (numpy, OpenCV and zlib release the
    GIL on large arrays, so independent pieces of work, such as a stream's time bins,
    share the cores; few are held at once). Inline when one thread is allowed. The
    threads' freed memory is handed back once all are done (:func:`trim_heap`)."""
    threads = min(solve_threads(), n, most or n)
    if threads <= 1:
        yield from (fn(k) for k in range(n))
        return
    first = min(n, threads * max(1, ahead))
    with ThreadPoolExecutor(threads) as ex:
        pending = deque(ex.submit(fn, k) for k in range(first))
        for k in range(first, n):
            done = pending.popleft().result()
            pending.append(ex.submit(fn, k))
            yield done
        while pending:
            yield pending.popleft().result()
    trim_heap()  # (what the threads freed: their arenas keep it resident otherwise)


def trim_heap() -> None:
    """Hand the C heap's free pages back to the system (glibc's ``malloc_trim(0)``; a no-op
    where the C library has none). Arrays of a few megabytes freed by the threads of
    :func:`in_order` stay in the allocator's arenas as resident memory; a stage that is
    about to make large arrays of its own calls this first, so its peak is what it holds,
    not what earlier stages freed."""
    import ctypes
    import ctypes.util

    global _MALLOC_TRIM
    if _MALLOC_TRIM is None:
        _MALLOC_TRIM = False
        name = ctypes.util.find_library("c")
        if name:
            with contextlib.suppress(OSError, AttributeError):
                _MALLOC_TRIM = ctypes.CDLL(name).malloc_trim
    if _MALLOC_TRIM:
        _MALLOC_TRIM(0)


_MALLOC_TRIM: Any = None

#: glibc's ``mallopt`` parameters, and what a worker's heap gets (:func:`reuse_heap`):
#: blocks under the mmap threshold are reused from the heap, and free memory at its top
#: is kept up to the trim threshold (the largest values glibc's own dynamic threshold
#: reaches on 64-bit systems).
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
HEAP_MMAP_THRESHOLD = 32 << 20
HEAP_TRIM_THRESHOLD = 64 << 20


def reuse_heap() -> bool:
    """Let this process's C heap reuse freed arrays (idempotent; False where the C
    library has no ``mallopt``).

    A Dask nanny starts its workers with ``MALLOC_TRIM_THRESHOLD_=65536``, which fixes
    glibc's thresholds at its defaults: every array over 128 kB is then a fresh ``mmap``
    whose pages fault in on first touch and go back to the system when freed, so numpy's
    temporaries cost about twice as much as in a process started plainly. The deblur's
    stages give memory back themselves where it matters (:func:`trim_heap`).
    """
    import ctypes.util

    name = ctypes.util.find_library("c")
    if not name:
        return False
    try:
        mallopt = ctypes.CDLL(name).mallopt
    except (OSError, AttributeError):
        return False
    return bool(
        mallopt(M_MMAP_THRESHOLD, HEAP_MMAP_THRESHOLD)
        and mallopt(M_TRIM_THRESHOLD, HEAP_TRIM_THRESHOLD)
    )


@contextlib.contextmanager
def opencv_single_threaded() -> Iterator[None]:
    """OpenCV on one thread inside the block (the process's setting restored after the
    last of such blocks open at once, on any thread, is left): for OpenCV calls made on
    threads of a pool that already shares the cores, whose own threads would only
    contend with it."""
    import cv2

    global _cv_depth, _cv_before
    with _cv_lock:
        if _cv_depth == 0:
            _cv_before = cv2.getNumThreads()
            cv2.setNumThreads(1)
        _cv_depth += 1
    try:
        yield
    finally:
        with _cv_lock:
            _cv_depth -= 1
            if _cv_depth == 0:
                cv2.setNumThreads(_cv_before)


def limit_threads() -> None:
    """Limit this process to one OpenCV / OpenMP / BLAS / OpenImageIO thread (idempotent),
    as a worker: its heap also reuses freed arrays (:func:`reuse_heap`).

    OpenImageIO and OpenEXR compress and decompress on their own thread pools: left
    alone, one worker spreads over every core, so N workers would not mean N cores.
    """
    global _threads_limited
    if _threads_limited:
        return
    reuse_heap()  # (a worker: see there)
    for k, v in WORKER_ENV.items():
        os.environ.setdefault(k, v)
    try:
        import cv2

        cv2.setNumThreads(1)
    except ImportError:  # pragma: no cover - cv2 is a dependency
        pass
    try:
        import OpenImageIO as oiio

        oiio.attribute("threads", 1)
        oiio.attribute("exr_threads", 1)
    except ImportError:  # pragma: no cover - OpenImageIO is a dependency
        pass
    _threads_limited = True


def quiet_dask_logs() -> None:
    """Keep Dask's and asyncio's chatter (INFO and DEBUG) out of vet's ``-v`` output."""
    names = ["distributed", "asyncio", "tornado", "bokeh"]
    names += [n for n in logging.root.manager.loggerDict if n.startswith("distributed.")]
    for name in names:
        logger = logging.getLogger(name)
        if logger.getEffectiveLevel() < logging.WARNING:
            logger.setLevel(logging.WARNING)


def _shutdown_logger_names() -> list[str]:
    names = list(SHUTDOWN_LOGGERS)
    names += [n for n in logging.root.manager.loggerDict if n.startswith("distributed.")]
    return names


@contextlib.contextmanager
def quiet_shutdown() -> Iterator[None]:
    """In this process, Dask's (and tornado's, asyncio's) loggers at CRITICAL while the
    block runs, their levels restored after it: for closing a client or a cluster."""
    saved = {}
    for name in _shutdown_logger_names():
        logger = logging.getLogger(name)
        saved[name] = logger.level
        logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for name, level in saved.items():
            logging.getLogger(name).setLevel(level)


class _ClosingFilter(logging.Filter):
    """Pass a record unless ``worker`` is closing (then CRITICAL only)."""

    def __init__(self, worker: Any):
        super().__init__()
        self.worker = worker

    def filter(self, record: logging.LogRecord) -> bool:
        from distributed.core import Status

        closing = self.worker.status in (Status.closing_gracefully, Status.closing, Status.closed)
        return record.levelno >= logging.CRITICAL or not closing


def quiet_when_closing(worker: Any) -> None:
    """Make the log handlers of ``worker``'s process pass CRITICAL records only once the
    worker is closing, so a heartbeat that meets the closed scheduler prints no
    traceback; until then every record passes."""
    handlers = set()
    for name in ("", *SHUTDOWN_LOGGERS):
        handlers.update(logging.getLogger(name).handlers)
    closing = _ClosingFilter(worker)
    for handler in handlers:
        handler.addFilter(closing)


def quiet_shutdown_plugin() -> Any:
    """A :class:`distributed.WorkerPlugin` that runs :func:`quiet_when_closing` on each
    worker as it starts (those a nanny restarts too). Made on demand: importing
    distributed costs a second, and most commands never start a cluster."""
    from distributed import WorkerPlugin

    class QuietWorkerShutdown(WorkerPlugin):
        name = "vet-quiet-shutdown"

        def setup(self, worker: Any) -> None:
            quiet_when_closing(worker)

    return QuietWorkerShutdown()


def _close(client: Any, cluster: Any) -> None:
    """Close the client, then the embedded cluster (its workers, then its scheduler),
    each within :data:`CLOSE_TIMEOUT_S`, with Dask's loggers quiet (:func:`quiet_shutdown`).
    A close that times out or fails is logged at debug level: the results are in."""
    log = logging.getLogger(__name__)
    with quiet_shutdown():
        for what, obj in (("client", client), ("cluster", cluster)):
            if obj is None:
                continue
            try:
                obj.close(timeout=CLOSE_TIMEOUT_S)
            except Exception as exc:  # noqa: BLE001 - a late close is not the run's failure
                log.debug("dask: closing the %s: %s: %s", what, type(exc).__name__, exc)


@contextlib.contextmanager
def environ_kept() -> Iterator[None]:
    """This process's environment as it was before the block, whatever the block set
    (a Dask nanny sets its workers' variables, ``OMP_NUM_THREADS=1`` among them, here
    before it spawns them: processes this one starts later must not inherit them)."""
    before = dict(os.environ)
    try:
        yield
    finally:
        for k in set(os.environ) - set(before):
            del os.environ[k]
        os.environ.update(before)


def parse_scheduler_address(text: str) -> str:
    """``tcp://HOST:PORT`` from ``tcp://HOST:PORT`` or ``HOST:PORT`` (IPv6 hosts in
    brackets), checked for its form only (nothing is contacted).

    Raises
    ------
    UsageError
        No port, a port outside 1..65535, another scheme than ``tcp``, no host
        (``option`` is ``--scheduler``: exit status 2 on the command line).
    """
    raw = str(text).strip()
    scheme, sep, rest = raw.partition("://")
    if not sep:
        scheme, rest = "tcp", raw
    form = "give tcp://HOST:PORT, e.g. tcp://10.0.0.5:8786"
    if scheme.lower() not in SCHEDULER_SCHEMES:
        raise UsageError(f"{raw!r}: scheme {scheme}:// is not supported; {form}", "--scheduler")
    host, colon, port = rest.rstrip("/").rpartition(":")
    if not colon or not host:
        raise UsageError(f"{raw!r}: no {'host' if colon else 'port'} given; {form}", "--scheduler")
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise UsageError(f"{raw!r}: port {port!r} is not in 1..65535; {form}", "--scheduler")
    if host.startswith("[") != host.endswith("]") or any(c.isspace() for c in host):
        raise UsageError(f"{raw!r}: host {host!r} is malformed; {form}", "--scheduler")
    return f"tcp://{host}:{int(port)}"


async def _identity(address: str, timeout_s: float) -> Any:
    from distributed.comm import connect

    comm = await connect(address, timeout=timeout_s)
    try:
        await comm.write({"op": "identity", "reply": True})
        return await comm.read()
    finally:
        await comm.close()


def check_scheduler(address: str, timeout_s: float | None = None) -> None:
    """Connect to ``address`` and ask who it is, within ``timeout_s`` (default
    :data:`HANDSHAKE_TIMEOUT_S`) all told; before a :class:`distributed.Client` is
    made, which waits longer and, when it fails, again when it is collected.

    Raises
    ------
    VetError
        Nothing answers, or what answers is no Dask scheduler (one line).
    """
    import asyncio
    import socket

    timeout_s = HANDSHAKE_TIMEOUT_S if timeout_s is None else timeout_s
    host, _, port = address.removeprefix("tcp://").rpartition(":")
    try:  # (a refused connection is told at once; Dask's connect retries it)
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as exc:
        why = exc.strerror or str(exc) or type(exc).__name__
        raise VetError(f"cannot reach the Dask scheduler at {address} ({why})") from None
    with quiet_shutdown():
        try:
            reply = asyncio.run(asyncio.wait_for(_identity(address, timeout_s), timeout_s))
        except (asyncio.TimeoutError, TimeoutError):
            reply = None
            why = f"no Dask scheduler answered within {timeout_s:.0f} s"
        except OSError as exc:
            reply = None
            why = " ".join(str(exc).split()) or type(exc).__name__
        except Exception as exc:  # noqa: BLE001 - whatever the other end said was no answer
            reply = None
            why = f"what answers there is no Dask scheduler ({type(exc).__name__})"
    if isinstance(reply, dict) and reply.get("type") == "Scheduler":
        return
    if reply is not None:
        why = "what answers there is no Dask scheduler"
    raise VetError(f"cannot reach the Dask scheduler at {address} ({why})")


#: Signals a terminal sends to its whole foreground process group (Ctrl-C, hang-up).
GROUP_SIGNALS = ("SIGINT", "SIGHUP")


@contextlib.contextmanager
def group_signals_held() -> Iterator[None]:
    """Hold :data:`GROUP_SIGNALS` (blocked) on this thread while the block runs, so that
    the threads it starts, and the processes those start (an embedded cluster's loop
    and its worker processes), inherit them blocked: Ctrl-C at the terminal then
    reaches the vet process alone, which closes the cluster, instead of every worker
    printing a KeyboardInterrupt traceback. A signal that arrives meanwhile is
    delivered here when the block ends. (A thread's own mask: any thread may hold them.)

    multiprocessing's resource tracker is started first: starting it *unblocks* SIGINT
    on the calling thread (``resource_tracker.ensure_running`` blocks it around its
    spawn, then unblocks rather than restores), which inside the block would let the
    processes spawned after it hear Ctrl-C."""
    if not hasattr(signal, "pthread_sigmask"):
        yield
        return
    from multiprocessing import resource_tracker

    resource_tracker.ensure_running()
    held = {getattr(signal, n) for n in GROUP_SIGNALS if hasattr(signal, n)}
    before = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


@contextlib.contextmanager
def dask_client(
    workers: int,
    scheduler: str | None = None,
    info: dict[str, Any] | None = None,
    timeout_s: float | None = None,
) -> Iterator[Any]:
    """A Dask client on ``scheduler``, else on an embedded LocalCluster of ``workers``.

    ``info`` is filled with ``executor`` (words), ``workers`` (count) and ``startup_s``.
    Raises :class:`~stages.errors.UsageError` for a malformed ``scheduler`` address
    (:func:`parse_scheduler_address`), :class:`~stages.errors.VetError` when no Dask
    scheduler answers there within :data:`HANDSHAKE_TIMEOUT_S` (:func:`check_scheduler`)
    or no worker joins it within ``timeout_s`` (default :data:`CONNECT_TIMEOUT_S`).
    """
    import distributed

    info = info if info is not None else {}
    timeout_s = CONNECT_TIMEOUT_S if timeout_s is None else timeout_s
    quiet_dask_logs()
    t0 = time.monotonic()
    cluster = None
    client = None
    try:
        if scheduler:
            address = parse_scheduler_address(scheduler)
            client = _remote_client(address, timeout_s)
            info["executor"] = f"dask scheduler {address}"
        else:
            # (the nanny's pre-spawn variables are its workers'; Ctrl-C is for vet; the
            # cluster is held before a signal held meanwhile is delivered: closed below)
            with environ_kept(), group_signals_held():
                cluster = distributed.LocalCluster(**_local_cluster_options(workers))
            client = distributed.Client(cluster, set_as_default=False)
            client.register_plugin(quiet_shutdown_plugin(), name="vet-quiet-shutdown")
            info["executor"] = f"dask LocalCluster, {workers} worker processes on 127.0.0.1"
        info["workers"] = len(client.scheduler_info().get("workers", {}))
        info["startup_s"] = round(time.monotonic() - t0, 3)
        yield client
    finally:
        _close(client, cluster)


def _local_cluster_options(workers: int) -> dict[str, Any]:
    """An embedded cluster: ``workers`` processes of one thread on the loopback."""
    return {
        "n_workers": workers,
        "threads_per_worker": 1,
        "processes": True,
        "host": "127.0.0.1",
        # (the scheduler's HTTP routes on a free loopback port: two clusters at once do
        # not compete for Dask's default 8787)
        "dashboard_address": "127.0.0.1:0",
        "worker_dashboard_address": None,
        "env": dict(WORKER_ENV),
        "silence_logs": logging.ERROR,  # worker heartbeat warnings under load: noise
    }


def _remote_client(scheduler: str, timeout_s: float) -> Any:
    """A client of the scheduler at ``scheduler`` once it answered
    (:func:`check_scheduler`) and a first worker joined it within ``timeout_s``."""
    import distributed

    check_scheduler(scheduler)
    try:
        client = distributed.Client(
            scheduler, timeout=f"{HANDSHAKE_TIMEOUT_S}s", set_as_default=False
        )
    except (OSError, TimeoutError) as exc:
        raise VetError(f"cannot reach the Dask scheduler at {scheduler} ({exc})") from None
    try:
        client.wait_for_workers(1, timeout=timeout_s)
    except (TimeoutError, OSError):
        _close(client, None)
        raise VetError(
            f"no Dask worker joined the scheduler at {scheduler} within {timeout_s:.0f} s"
        ) from None
    return client


def _import_modules(names: tuple[str, ...]) -> None:
    """Import ``names`` (on a worker: what its first task would import)."""
    import importlib

    for name in names:
        importlib.import_module(name)


class ClientSoon:
    """:func:`dask_client` started on a thread of its own when made, so that the cluster
    starts (an embedded one's processes spawned, an existing one's scheduler reached)
    and its workers import ``warm`` (module names) while the caller goes on with work of
    its own; :meth:`client` waits for it. A context manager: leaving it closes the client
    (and an embedded cluster) as :func:`dask_client` does, also when it was never asked
    for. :meth:`client` raises what starting raised (:class:`~stages.errors.VetError`
    where the scheduler cannot be reached or no worker joins it); ``info`` is
    :func:`dask_client`'s."""

    def __init__(
        self, workers: int, scheduler: str | None = None, warm: tuple[str, ...] = ()
    ) -> None:
        self.info: dict[str, Any] = {}
        self._started: contextlib.AbstractContextManager | None = None
        self._client: Any = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(
            target=self._start, args=(workers, scheduler, warm), name="vet-dask-start"
        )
        self._thread.start()

    def _start(self, workers: int, scheduler: str | None, warm: tuple[str, ...]) -> None:
        try:
            started = dask_client(workers, scheduler, self.info)
            self._client = started.__enter__()
            self._started = started
        except BaseException as exc:  # noqa: BLE001 - raised where the client is asked for
            self._error = exc
            return
        if warm:
            try:
                self._client.run(_import_modules, warm)
            except Exception as exc:  # noqa: BLE001 - the tasks import them anyway, and say so
                logging.getLogger(__name__).debug(
                    "dask: warming the workers: %s: %s", type(exc).__name__, exc
                )

    def client(self) -> Any:
        """The client, once started (raises what starting raised)."""
        self._thread.join()
        if self._error is not None:
            raise self._error
        return self._client

    def __enter__(self) -> ClientSoon:
        return self

    def __exit__(self, *exc: object) -> None:
        self._thread.join()
        if self._started is not None:
            self._started.__exit__(None, None, None)
