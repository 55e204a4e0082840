"""Executors of the study engine: in this process, or on Dask (a local cluster, one
worker per GPU, or an existing scheduler).

An :class:`Executor` runs submitted (key, function, args) jobs and yields them as they
finish. ``workers=0``: :class:`InProcess`; otherwise Dask: a ``LocalCluster`` of
``workers`` single-threaded worker processes (default: one per CPU), or the cluster
whose scheduler listens at ``scheduler`` (``tcp://`` or ``tls://HOST:PORT``; TLS
settings come from Dask's configuration, ``distributed.comm.tls.*``, or
``security=``); ``gpus=N``: a local cluster of one worker per GPU (worker i sees only
GPU i). Local worker processes get :data:`WORKER_ENV`. :class:`Lazy` starts its
executor only when the first job arrives.
"""

from __future__ import annotations

import collections
import logging
import os
import re
import socket
import time
from collections.abc import Callable, Iterator
from typing import Any

from cdma_lidar.errors import ConfigError, LinkError

__all__ = [
    "WORKER_ENV",
    "Executor",
    "InProcess",
    "Lazy",
    "check_executor",
    "make_executor",
]

log = logging.getLogger(__name__)

_SCHEDULER_RE = re.compile(r"^(tcp|tls|inproc|ucx)://[^\s/]+$")

class Executor:
    """Runs submitted (key, function, args) jobs; :meth:`completed` yields (key, result |
    None, exception | None) as they finish, including jobs submitted while it iterates."""

    description = ""
    #: jobs that run at once
    slots = 1

    def submit(self, key: str, fn: Callable[..., Any], args: tuple) -> None:
        raise NotImplementedError

    def completed(self) -> Iterator[tuple[str, Any, BaseException | None]]:
        raise NotImplementedError

    def close(self) -> None:
        pass


class InProcess(Executor):
    description = "in-process (no Dask)"

    def __init__(self) -> None:
        self._queue: collections.deque[tuple[str, Callable[..., Any], tuple]] = \
            collections.deque()

    def submit(self, key, fn, args):  # type: ignore[no-untyped-def]
        self._queue.append((key, fn, args))

    def completed(self):  # type: ignore[no-untyped-def]
        while self._queue:
            key, fn, args = self._queue.popleft()
            try:
                yield key, fn(*args), None
            except Exception as exc:
                yield key, None, exc


def _probe_scheduler(address: str, timeout_s: float) -> None:
    """Fail in at most ``timeout_s`` with one line when a tcp/tls scheduler cannot be reached.

    Dask retries a refused or silent address for its whole connect timeout and then logs
    many lines; one TCP connection attempt answers the common case (a wrong host or port).
    """
    scheme, _, where = address.partition("://")
    if scheme not in ("tcp", "tls"):
        return
    host, _, port = where.rpartition(":")
    if not host or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise ConfigError(f"--scheduler {address!r}: expected {scheme}://HOST:PORT with a "
                          "port from 1 to 65535", "scheduler")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s) as sock:
            if scheme == "tcp":  # a Dask server speaks first: an 8-byte little-endian length
                head = sock.recv(8, socket.MSG_WAITALL)
                if len(head) < 8 or int.from_bytes(head, "little") > 1 << 30:
                    raise LinkError(f"--scheduler {address!r}: the server there is not a Dask "
                                    "scheduler; check the address")
    except OSError as exc:
        if isinstance(exc, LinkError):
            raise
        raise LinkError(f"--scheduler {address!r}: cannot reach the Dask scheduler "
                        f"({exc.strerror or 'no answer in ' + format(timeout_s, 'g') + ' s'}); "
                        "check the address and that the scheduler runs") from None


#: Environment of local worker processes: one single-threaded worker per core, so the
#: receive chain runs one thread in each (Dask already sets the BLAS libraries to one).
WORKER_ENV = {"CDMA_LIDAR_THREADS": "1"}


class Dask(Executor):
    """A dask.distributed Client on a LocalCluster or an existing scheduler.

    ``gpus`` > 0: a local cluster of that many single-threaded workers, worker i seeing
    only GPU i (``CUDA_VISIBLE_DEVICES``), so the receive chain's ``method="auto"`` finds
    one device per worker (one worker per GPU).
    """

    def __init__(self, workers: int | None, scheduler: str | None,
                 security: Any = None, processes: bool = True,
                 connect_timeout_s: float = 10.0, gpus: int = 0) -> None:
        try:
            # optional dependency (extra "study"): only sweeps on Dask need it
            from distributed import Client, LocalCluster, as_completed
        except ImportError:
            raise ConfigError("running a study on Dask needs dask.distributed: install "
                              "'cdma-lidar[study]' (or use --workers 0 to run in this process)",
                              "workers") from None
        if not log.isEnabledFor(logging.DEBUG):  # Dask logs every scheduler event at INFO
            logging.getLogger("distributed").setLevel(logging.WARNING)
        self._cluster = None
        if scheduler is not None:
            if not _SCHEDULER_RE.match(scheduler):
                raise ConfigError(f"--scheduler {scheduler!r}: expected tcp://HOST:PORT or "
                                  "tls://HOST:PORT", "scheduler")
            _probe_scheduler(scheduler, min(connect_timeout_s, 3.0))
            try:
                self.client = Client(scheduler, timeout=f"{connect_timeout_s}s", security=security,
                                     set_as_default=False)
            except (OSError, TimeoutError, ValueError) as exc:
                raise LinkError(f"--scheduler {scheduler!r}: cannot reach the Dask scheduler "
                                f"({type(exc).__name__}: {str(exc).splitlines()[0][:120]})"
                                ) from None
            self.description = f"dask scheduler {scheduler}"
            self.slots = max(1, sum(self.client.nthreads().values()))
        else:
            n = gpus or (workers if workers is not None else (os.cpu_count() or 1))
            # no dashboard; the scheduler's small HTTP server (health, metrics) on a free
            # loopback port rather than 8787, which another cluster may hold
            if gpus:  # one worker process per device, each seeing only its own
                self._cluster = _gpu_cluster(gpus)
            else:
                self._cluster = LocalCluster(n_workers=n, threads_per_worker=1,
                                             processes=processes,
                                             host="127.0.0.1" if processes else None,
                                             dashboard_address="127.0.0.1:0",
                                             scheduler_kwargs={"dashboard": False},
                                             silence_logs=logging.ERROR,
                                             **({"env": WORKER_ENV} if processes else {}))
            self.client = Client(self._cluster, set_as_default=False)
            if gpus:
                self.client.wait_for_workers(gpus, timeout=60)
            self.slots = n
            self.description = (f"dask LocalCluster, {n} worker "
                                f"{'processes' if processes else 'threads'}"
                                + (", one per GPU" if gpus else ""))
        self._done = as_completed(loop=self.client.loop)
        self._keys: dict[Any, str] = {}

    def submit(self, key, fn, args):  # type: ignore[no-untyped-def]
        fut = self.client.submit(fn, *args, key=f"study-{key}", pure=False)
        self._keys[fut] = key
        self._done.add(fut)

    def completed(self):  # type: ignore[no-untyped-def]
        try:
            for fut in self._done:
                key = self._keys.pop(fut)
                try:
                    yield key, fut.result(), None
                except Exception as exc:
                    yield key, None, exc
                finally:
                    fut.release()
        finally:
            for fut in list(self._keys):
                if not fut.done():
                    fut.cancel()
            self._keys.clear()
            self._done.clear()

    def close(self) -> None:
        self.client.close()
        if self._cluster is not None:
            self._cluster.close()


def _gpu_cluster(gpus: int) -> Any:
    """A local Dask cluster of ``gpus`` single-threaded worker processes, worker i with
    ``CUDA_VISIBLE_DEVICES=i``."""
    from distributed import Nanny, Scheduler, SpecCluster  # optional dependency, as above
    workers = {f"gpu-{i}": {"cls": Nanny, "options": {
        "nthreads": 1, "host": "127.0.0.1", "silence_logs": logging.ERROR,
        "env": {**WORKER_ENV, "CUDA_VISIBLE_DEVICES": str(i)}}} for i in range(gpus)}
    scheduler = {"cls": Scheduler, "options": {"host": "127.0.0.1", "dashboard": False,
                                               "dashboard_address": "127.0.0.1:0"}}
    return SpecCluster(workers=workers, scheduler=scheduler, silence_logs=logging.ERROR)


class Lazy(Executor):
    """Starts its executor (a Dask cluster, say) only when the first job is submitted:
    a resumed run with nothing missing starts nothing."""

    def __init__(self, factory: Callable[[], Executor]) -> None:
        self._factory = factory
        self._real: Executor | None = None
        #: seconds it took to start (0 until started)
        self.start_s = 0.0

    def _get(self) -> Executor:
        if self._real is None:
            t0 = time.monotonic()
            self._real = self._factory()
            self.start_s = time.monotonic() - t0
        return self._real

    @property
    def description(self) -> str:  # type: ignore[override]
        return self._real.description if self._real is not None else "none (nothing to run)"

    @property
    def slots(self) -> int:  # type: ignore[override]
        return self._get().slots

    def submit(self, key, fn, args):  # type: ignore[no-untyped-def]
        self._get().submit(key, fn, args)

    def completed(self):  # type: ignore[no-untyped-def]
        return iter(()) if self._real is None else self._real.completed()

    def close(self) -> None:
        if self._real is not None:
            self._real.close()


def check_executor(workers: int | None, scheduler: str | None, gpus: int = 0) -> None:
    if workers is not None and scheduler is not None:
        raise ConfigError("give --workers or --scheduler, not both", "workers")
    if workers is not None and not (isinstance(workers, int) and 0 <= workers <= 4096):
        raise ConfigError(f"--workers {workers!r}: expected 0..4096 (0: in this process)",
                          "workers")
    if not (isinstance(gpus, int) and 0 <= gpus <= 1024):
        raise ConfigError(f"--gpus {gpus!r}: expected 0..1024", "gpus")
    if gpus and (scheduler is not None or workers is not None):
        raise ConfigError("--gpus starts one local worker per GPU: give it without "
                          "--workers and --scheduler", "gpus")
    if scheduler is not None and not _SCHEDULER_RE.match(scheduler):
        raise ConfigError(f"--scheduler {scheduler!r}: expected tcp://HOST:PORT or "
                          "tls://HOST:PORT", "scheduler")


def make_executor(workers: int | None = None, scheduler: str | None = None, *,
                  security: Any = None, processes: bool = True,
                  connect_timeout_s: float = 10.0, gpus: int = 0) -> Executor:
    """``workers=0``: in this process; otherwise Dask (local cluster or ``scheduler``);
    ``gpus`` > 0: a local cluster of one worker per GPU."""
    check_executor(workers, scheduler, gpus)
    if workers == 0:
        return InProcess()
    return Dask(workers, scheduler, security=security, processes=processes,
                 connect_timeout_s=connect_timeout_s, gpus=gpus)
