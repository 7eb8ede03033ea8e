"""The one parallel runner of the project: tasks on dask.distributed (or in-process).

Every parallel path goes through `Runner`: studies (`./fluxdrive study`), replay sweeps
(`replay --sweep -j N`) and the experiments' searches.  Three modes, one API:

    Runner("serial")                 in this process, in order (small sweeps, --graph runs,
                                     debugging; no cluster is started)
    Runner("local", workers=N)       a dask LocalCluster of N single-threaded worker
                                     processes on 127.0.0.1 (N = every core by default)
    Runner("tcp://HOST:PORT")        an existing cluster (`dask scheduler` + `dask worker`)

A task is `fn(payload) -> value` with `fn` a module-level function (dask pickles it by
reference, so the workers need the same fluxdrive).  Worker processes: the compiled kernels
hold the GIL, so one thread per process is what scales.  A task that raises is retried once
(on any worker); if it fails again it comes back as an `Outcome` with ok=False, its payload and
the error -- never dropped.  A worker that dies takes no result with it: the scheduler runs
its tasks again elsewhere.
"""

from __future__ import annotations

import os
import sys
import time
import traceback
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

RETRIES = 1  # a failed task is run once more before it is reported


@dataclass
class Outcome:
    key: Any
    payload: Any
    ok: bool
    value: Any = None
    error: str = ""
    attempts: int = 1
    worker: str = ""


@dataclass
class Progress:
    """Counts and an ETA printed on stderr as tasks finish (every `every_s` seconds at most:
    2 s on a terminal, 10 s into a log; and at the end)."""

    total: int
    label: str = "run"
    every_s: float = field(default_factory=lambda: 2.0 if sys.stderr.isatty() else 10.0)
    echo: bool = True
    done: int = 0
    failed: int = 0
    t0: float = field(default_factory=time.perf_counter)
    _last: float = 0.0
    _first: float = 0.0  # when the first task finished: the rate excludes the start-up

    def update(self, ok: bool) -> None:
        self.done += 1
        self.failed += 0 if ok else 1
        now = time.perf_counter()
        if self.done == 1:
            self._first = now
        if self.echo and (now - self._last >= self.every_s or self.done == self.total):
            self._last = now
            sys.stderr.write(self.line() + "\n")
            sys.stderr.flush()

    def line(self) -> str:
        now = time.perf_counter()
        el = now - self.t0
        rate = (self.done - 1) / (now - self._first) if self.done > 1 and now > self._first else 0.0
        left = self.total - self.done
        eta = f"ETA {_hms(left / rate)}" if rate > 0 and left else "done" if not left else "ETA ?"
        fail = f", {self.failed} failed" if self.failed else ""
        return (
            f"[{self.label}] {self.done}/{self.total}{fail}, {rate:.2f} tasks/s, "
            f"{_hms(el)} elapsed, {eta}"
        )


def _hms(s: float) -> str:
    s = int(round(s))
    return (
        f"{s // 3600}h{s // 60 % 60:02d}m{s % 60:02d}s"
        if s >= 3600
        else f"{s // 60}m{s % 60:02d}s"
        if s >= 60
        else f"{s}s"
    )


def _call(fn: Callable[[Any], Any], payload: Any) -> tuple[bool, Any, str, str]:
    """Run one task; never raises (the error text travels back instead)."""
    try:
        return True, fn(payload), "", _worker_name()
    except Exception as exc:  # reported with the payload by the caller
        return False, None, f"{type(exc).__name__}: {exc}\n{traceback.format_exc()}", _worker_name()


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except (ImportError, ValueError):
        return f"local:{os.getpid()}"


class Runner:
    """Run tasks serially, on a LocalCluster, or on an existing dask cluster (see module doc).
    Use as a context manager; the cluster (if this runner started one) stops on exit."""

    def __init__(
        self,
        mode: str = "local",
        workers: int | None = None,
        retries: int = RETRIES,
        quiet: bool = True,
    ):
        self.mode = mode
        self.retries = retries
        self.client = None
        self.cluster = None
        if mode == "serial":
            self.workers = 1
            return
        from distributed import Client, LocalCluster

        if mode == "local":
            n = max(1, workers or os.cpu_count() or 1)
            if n == 1 and workers is None:
                self.mode, self.workers = "serial", 1
                return
            self.cluster = LocalCluster(
                n_workers=n,
                threads_per_worker=1,
                processes=True,
                host="127.0.0.1",
                dashboard_address="127.0.0.1:0",
                silence_logs=40 if quiet else 30,
            )
            self.client = Client(self.cluster)
        elif mode.startswith("tcp://"):
            self.client = Client(mode, timeout="20s")
        else:
            raise ValueError(
                f"runner mode must be 'serial', 'local' or tcp://HOST:PORT, got {mode!r}"
            )
        self.workers = len(self.client.scheduler_info()["workers"]) or 1

    @property
    def address(self) -> str:
        return self.client.scheduler.address if self.client is not None else "in-process"

    def close(self) -> None:
        if self.cluster is not None and self.client is not None:
            # our own cluster's workers go first, while the scheduler still answers: closed
            # the other way round, a worker's heartbeat can meet a closed scheduler and its
            # process logs an ERROR with a traceback as the command ends
            try:
                self.cluster.scale(0)
                t_end = time.monotonic() + 20.0
                while self.client.scheduler_info()["workers"] and time.monotonic() < t_end:
                    time.sleep(0.05)
            except Exception:  # noqa: BLE001 - closing anyway, below
                pass
        if self.client is not None:
            self.client.close()
            self.client = None
        if self.cluster is not None:
            self.cluster.close()
            self.cluster = None

    def __enter__(self) -> Runner:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ running
    def run_unordered(
        self,
        fn: Callable[[Any], Any],
        items: Iterable[tuple[Any, Any]],
        progress: Progress | None = None,
    ) -> Iterator[Outcome]:
        """(key, payload) items -> Outcomes as the tasks finish (any order)."""
        items = list(items)
        if self.client is None:
            for key, payload in items:
                out: Outcome | None = None
                for attempt in range(1, self.retries + 2):
                    ok, val, err, who = _call(fn, payload)
                    out = Outcome(key, payload, ok, val, err, attempt, who)
                    if ok:
                        break
                assert out is not None  # the loop runs at least once
                if progress is not None:
                    progress.update(out.ok)
                yield out
            return
        from distributed import as_completed

        futs: dict[Any, tuple[Any, Any, int]] = {}
        submitted = []
        for key, payload in items:
            f = self.client.submit(_call, fn, payload, pure=False)
            futs[f.key] = (key, payload, 1)
            submitted.append(f)
        ac = as_completed(submitted)
        for f in ac:
            key, payload, attempt = futs.pop(f.key)
            try:
                ok, val, err, who = f.result()
            except Exception as exc:  # the task itself never raises: the cluster lost it
                ok, val, err, who = False, None, f"{type(exc).__name__}: {exc}", ""
            f.release()
            if not ok and attempt <= self.retries:
                g = self.client.submit(_call, fn, payload, pure=False)
                futs[g.key] = (key, payload, attempt + 1)
                ac.add(g)
                continue
            out = Outcome(key, payload, ok, val, err, attempt, who)
            if progress is not None:
                progress.update(ok)
            yield out

    def map(
        self, fn: Callable[[Any], Any], payloads: list[Any], progress: Progress | None = None
    ) -> list[Any]:
        """Values in the order of `payloads`; raises if a task failed after its retry (for
        callers that need every value, e.g. an experiment's search step)."""
        res: list[Any] = [None] * len(payloads)
        for o in self.run_unordered(fn, enumerate(payloads), progress):
            if not o.ok:
                raise TaskFailed(o)
            res[o.key] = o.value
        return res


class TaskFailed(RuntimeError):
    def __init__(self, o: Outcome):
        super().__init__(
            f"task {o.key} failed after {o.attempts} attempt(s): "
            f"{o.error.splitlines()[0] if o.error else '?'}"
        )
        self.outcome = o


def runner_from_args(scheduler: str | None, workers: int | None) -> Runner:
    """--scheduler tcp://HOST:PORT wins; else a LocalCluster of `workers` (every core by
    default; 1 runs in-process)."""
    if scheduler:
        return Runner(scheduler)
    if workers is not None and workers <= 1:
        return Runner("serial")
    return Runner("local", workers=workers)
