"""Where a campaign's runs execute: a local pool of worker processes, or a Ray cluster.

Both executors are context managers with ``map_unordered(fn, items, on_crash)``: each item's
``fn(item)`` as it finishes, in completion order. ``fn`` catches a run's own failure; a worker
that dies under a run (a segfault, the kernel's OOM killer, a lost Ray node) gives
``on_crash(item, reason)`` for that run instead, and the sweep goes on.

The local pool is a few lines of multiprocessing rather than ``concurrent.futures`` because it
must know which run a dead worker held (to record that run, and only it, as failed) and start a
replacement; its workers are spawned (not forked: MuJoCo and numba threads do not survive a
fork) and die with this process (``PR_SET_PDEATHSIG``), as a supervised service does.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
from collections.abc import Callable, Iterable, Iterator
from multiprocessing.connection import Connection, wait
from typing import Any

from services.runtime.realtime import die_with_parent

STOP_GRACE_S = 5.0  # [s] a worker asked to stop has this long before SIGTERM, then as long again before SIGKILL
RAY_LOCAL = "local"  # --ray local: a private Ray instance on 127.0.0.1, stopped with the campaign
RAY_SINGLE_MACHINE_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"

Crash = Callable[[Any, str], Any]


def _worker_main(conn: Connection, parent_pid: int) -> None:
    """A worker: runs ``(fn, item)`` jobs until told to stop (``None``) or its parent is gone."""
    die_with_parent(parent_pid, signal.SIGKILL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the parent's to handle: it stops the workers
    while True:
        try:
            job = conn.recv()
        except EOFError:  # the parent closed its end
            return
        if job is None:
            return
        fn, item = job
        conn.send(fn(item))


class _Worker:
    def __init__(self, ctx: mp.context.SpawnContext) -> None:
        self.conn, child = ctx.Pipe()
        self.process = ctx.Process(target=_worker_main, args=(child, os.getpid()), daemon=True, name="campaign-worker")
        self.process.start()
        child.close()
        self.item: Any = None
        self.busy = False

    def give(self, fn: Callable[[Any], Any], item: Any) -> None:
        self.item, self.busy = item, True
        self.conn.send((fn, item))

    def stop(self) -> None:
        try:
            self.conn.send(None)
        except OSError:  # already gone
            pass
        self.process.join(STOP_GRACE_S)
        for end in (self.process.terminate, self.process.kill):
            if self.process.is_alive():
                end()
                self.process.join(STOP_GRACE_S)
        self.conn.close()


class LocalPool:
    """``workers`` processes on this machine, each running one run at a time."""

    def __init__(self, workers: int) -> None:
        if workers < 1:
            raise ValueError("a pool needs at least one worker")
        self.workers = workers
        self._ctx = mp.get_context("spawn")
        self._live: list[_Worker] = []

    def __enter__(self) -> LocalPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Stops every worker, whatever state it is in."""
        while self._live:
            self._live.pop().stop()

    def map_unordered(self, fn: Callable[[Any], Any], items: Iterable[Any], on_crash: Crash) -> Iterator[Any]:
        pending = list(items)[::-1]  # popped from the end: submission order
        while len(self._live) < min(self.workers, len(pending)):
            self._live.append(_Worker(self._ctx))
        while pending or any(w.busy for w in self._live):
            for worker in self._live:
                if not worker.busy and pending:
                    worker.give(fn, pending.pop())
            busy = [w for w in self._live if w.busy]
            ready = set(wait([w.conn for w in busy] + [w.process.sentinel for w in busy]))
            for worker in busy:
                if worker.conn in ready:
                    try:
                        result = worker.conn.recv()
                    except (EOFError, OSError):  # died while answering
                        result = self._replace(worker, on_crash)
                    else:
                        worker.busy = False
                    yield result
                elif worker.process.sentinel in ready:
                    yield self._replace(worker, on_crash)

    def _replace(self, worker: _Worker, on_crash: Crash) -> Any:
        """The dead worker's run is recorded as crashed; a fresh worker takes its place."""
        worker.process.join()
        reason = f"worker process {worker.process.pid} died (exit code {worker.process.exitcode})"
        worker.conn.close()
        self._live[self._live.index(worker)] = _Worker(self._ctx)
        return on_crash(worker.item, reason)


class RayPool:
    """Runs as Ray tasks (one CPU each) on the cluster at ``address`` (``local``: a private instance).

    Ray is an optional extra (``pip install -e '.[cluster]'``). Ray's usage statistics stay off.
    A private instance listens on 127.0.0.1 only when this process has not imported Ray before
    (Ray fixes its node address at import). It stops with the campaign however the campaign
    ends, except by SIGKILL: then its GCS, raylet and workers go, but Ray's dashboard agent and
    runtime-env agent were seen still running 45 s later (Ray 2.60).
    """

    def __init__(self, address: str, workers: int) -> None:
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        if address == RAY_LOCAL:
            # Ray's single-machine mode (its default on macOS and Windows): the node's address is the
            # loopback one and every Ray server listens on 127.0.0.1 only. Read when ray is imported.
            os.environ.setdefault(RAY_SINGLE_MACHINE_ENV, "0")
        try:
            import ray
        except ImportError:
            raise ImportError("--ray needs Ray: pip install -e '.[cluster]'") from None
        self._ray = ray
        if address == RAY_LOCAL:
            ray.init(address="local", num_cpus=workers, include_dashboard=False, _node_ip_address="127.0.0.1",
                     log_to_driver=False, configure_logging=False)
        else:
            ray.init(address=address, log_to_driver=False, configure_logging=False)

    def __enter__(self) -> RayPool:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Disconnects; a private instance (``local``) is stopped with all its processes."""
        self._ray.shutdown()

    def map_unordered(self, fn: Callable[[Any], Any], items: Iterable[Any], on_crash: Crash) -> Iterator[Any]:
        ray = self._ray
        task = ray.remote(num_cpus=1, max_retries=0)(fn)  # a run that killed its worker is recorded, not repeated
        running = {task.remote(item): item for item in items}
        while running:
            ready, _ = ray.wait(list(running), num_returns=1)
            for ref in ready:
                item = running.pop(ref)
                try:
                    yield ray.get(ref)
                except ray.exceptions.RayError as exc:
                    yield on_crash(item, f"{type(exc).__name__}: {exc}")
