"""A real-time thread for the host's hot path (no ROS): the bench PC's side of a deadline.

The host answers every sample of the drive within its deadline (split mode: the drive's
reference timeout) only if nothing else on the PC can hold it up for milliseconds. What a
Linux process can do about that, applied to the *calling thread* by :func:`enter_realtime`:

* ``SCHED_FIFO`` at ``priority`` (1..99): no normal (``SCHED_OTHER``) task -- a busy core,
  a compiler, a browser -- preempts the thread; it needs root or ``CAP_SYS_NICE`` (or an
  ``rtprio`` limit in ``/etc/security/limits.conf``);
* ``mlockall(MCL_CURRENT | MCL_FUTURE)``: no page of the process is paged out (a page fault
  on the hot path costs milliseconds); needs ``CAP_IPC_LOCK`` or a large ``memlock`` limit;
* CPU affinity to ``cpu``: the thread stays on one core (ideally one isolated from the
  scheduler, ``isolcpus=`` on the kernel command line, docs/bringup.md);
* and, for the loop itself, :class:`GcPause`: the objects alive at the start are frozen
  (``gc.freeze``: never scanned again), automatic collection is off and the young
  generations (0 and 1) are collected at a moment the loop chooses, once a second
  (:meth:`GcPause.collect_young`, right after an answer went out: microseconds), so a
  collection never lands between a sample and its answer. Cyclic garbage that outlives two
  such collections waits for the loop's end.

What could not be applied is no error -- the loop runs, with a late answer more likely --
but it is said in one line each (:attr:`RealtimeReport.notes`), so a bench log shows why a
deadline was missed.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import gc
import os
import time
from dataclasses import dataclass, field
from typing import Any

__all__ = ["GcPause", "HotPath", "RealtimeReport", "enter_realtime"]

_MCL_CURRENT, _MCL_FUTURE = 1, 2


@dataclass
class RealtimeReport:
    """What :func:`enter_realtime` got for the calling thread."""

    policy: str = "SCHED_OTHER"  # SCHED_FIFO when the real-time priority took effect
    priority: int = 0
    memory_locked: bool = False
    cpu: int | None = None  # the core the thread is pinned to, None: any
    notes: list[str] = field(default_factory=list)  # one line per thing not applied

    @property
    def realtime(self) -> bool:
        return self.policy == "SCHED_FIFO"

    def as_dict(self) -> dict[str, Any]:
        return {
            "policy": self.policy,
            "priority": self.priority,
            "memory_locked": self.memory_locked,
            "cpu": self.cpu,
            "notes": list(self.notes),
        }

    def line(self) -> str:
        """One line for a log: what the thread runs with."""
        cpu = "any core" if self.cpu is None else f"core {self.cpu}"
        mem = "memory locked" if self.memory_locked else "memory not locked"
        pol = f"{self.policy} {self.priority}" if self.realtime else self.policy
        return f"hot path: {pol}, {mem}, {cpu}"


def enter_realtime(
    priority: int = 80, cpu: int | None = None, lock_memory: bool = True
) -> RealtimeReport:
    """Make the calling thread a real-time one (see the module doc): ``SCHED_FIFO`` at
    ``priority`` (0: leave the policy as it is), pinned to ``cpu`` (None: any core; a core
    this process may not use is a note), the process's memory locked (``lock_memory``).
    Never raises for want of permission: each thing not applied is a line in ``notes``."""
    rep = RealtimeReport()
    if priority > 0:
        if not 1 <= priority <= 99:
            raise ValueError(f"real-time priority must be in 1..99, not {priority}")
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
            rep.policy, rep.priority = "SCHED_FIFO", priority
        except (PermissionError, OSError, AttributeError) as exc:
            rep.notes.append(
                f"SCHED_FIFO {priority} refused ({_why(exc)}): the hot path runs at normal "
                "priority (needs root, CAP_SYS_NICE or an rtprio limit)"
            )
    if cpu is not None:
        try:
            allowed = os.sched_getaffinity(0)
            if cpu not in allowed:
                rep.notes.append(f"core {cpu} is not one this process may use {sorted(allowed)}")
            else:
                os.sched_setaffinity(0, {cpu})
                rep.cpu = cpu
        except OSError as exc:
            rep.notes.append(f"pinning to core {cpu} refused ({_why(exc)})")
    if lock_memory:
        err = _mlockall()
        if err:
            rep.notes.append(
                f"mlockall refused ({err}): pages may be swapped out (needs CAP_IPC_LOCK or "
                "a memlock limit)"
            )
        else:
            rep.memory_locked = True
    return rep


def _mlockall() -> str:
    """'' when the process's memory is locked now and in future, else why not."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)
        if libc.mlockall(_MCL_CURRENT | _MCL_FUTURE) == 0:
            return ""
        return os.strerror(ctypes.get_errno())
    except (OSError, AttributeError) as exc:
        return _why(exc)


def _why(exc: BaseException) -> str:
    return getattr(exc, "strerror", None) or str(exc) or type(exc).__name__


class GcPause:
    """Python's cyclic garbage collector kept off the hot path: on entry everything alive is
    frozen and automatic collection disabled; :meth:`collect_young` collects the young
    generations (0 and 1) at most every ``every_s`` (call it right after an answer went out,
    or when idle); on exit
    collection is as it was. Counts the collections and the longest one."""

    def __init__(self, every_s: float = 1.0) -> None:
        self.every_s = every_s
        self.collections = 0
        self.longest_s = 0.0
        self._next = 0.0
        self._was_enabled = True

    def __enter__(self) -> GcPause:
        self._was_enabled = gc.isenabled()
        gc.collect()
        gc.freeze()
        gc.disable()
        self._next = time.perf_counter() + self.every_s
        return self

    def collect_young(self) -> None:
        now = time.perf_counter()
        if now < self._next:
            return
        gc.collect(1)
        t = time.perf_counter()
        self.longest_s = max(self.longest_s, t - now)
        self.collections += 1
        self._next = t + self.every_s

    def __exit__(self, *exc: object) -> None:
        gc.unfreeze()
        if self._was_enabled:
            gc.enable()


class HotPath:
    """The host's hot path as one context, for the thread that polls the bus and answers
    (the bench_bridge node's CAN thread, the paced benchmark's host): on entry
    :func:`enter_realtime` for the calling thread (``priority`` 0: no real-time policy,
    memory not locked) and a :class:`GcPause`; call :meth:`after_answer` once an answer went
    out (a young collection when one is due). ``report`` says what took effect."""

    def __init__(self, priority: int = 80, cpu: int | None = None, gc_every_s: float = 1.0) -> None:
        self.priority, self.cpu = int(priority), cpu
        self.gc = GcPause(gc_every_s)
        self.report = RealtimeReport()

    def __enter__(self) -> HotPath:
        if self.priority > 0:
            self.report = enter_realtime(self.priority, self.cpu)
        elif self.cpu is not None:
            self.report = enter_realtime(0, self.cpu, lock_memory=False)
        if self.priority <= 0:
            self.report.notes.append("real-time priority not asked for (priority 0)")
        self.gc.__enter__()
        return self

    def after_answer(self) -> None:
        self.gc.collect_young()

    def __exit__(self, *exc: object) -> None:
        self.gc.__exit__(*exc)
