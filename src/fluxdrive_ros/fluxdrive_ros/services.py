"""Services answered beside the data path: a process's service servers live on a thread of
their own, so a busy data path (a lockstep loop, a flood of samples) cannot leave a request
waiting in its queue.

`ServiceSide(nodes)` (the runner starts one per process) moves every service server of the
process's nodes -- the six parameter services rclpy gives each node, the controller's and the
bridge's fault reset and arming -- onto a hidden node of the process (`_fluxdrive_services_<pid>`,
the same service names, so clients see no change) that a SingleThreadedExecutor spins on its
own thread, at a raised OS priority where the OS permits it (one log line where it does not).

What a request may touch decides where it runs:
- reading parameters (`get_parameters`, `describe_parameters`, `list_parameters`,
  `get_parameter_types`) is answered on the service thread at once;
- everything that changes a node (setting parameters, a fault reset, arming) is handed to the
  data path's executor and runs there between two of its callbacks -- as it did before this
  thread existed -- so a change never lands inside a callback and takes effect from a sample
  the node names (the graph identity and live-tuning tests hold bit for bit); the service
  thread waits for it and sends the answer.

A node that needs its service to run on the data path's thread needs no change: the move is
by the kind of service, see `READ_ONLY`.
"""

from __future__ import annotations

import os
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

# parameter services that only read: answered on the service thread
READ_ONLY = ("describe_parameters", "get_parameters", "get_parameter_types", "list_parameters")
# the service thread's nice value where the OS permits it (root or CAP_SYS_NICE)
SERVICE_NICE = -5
# the service thread's executor polls for its stop this often
JOB_POLL_S = 0.005
"""How often the data path looks for handed-over requests [s] (a steady-clock timer)."""
POLL_S = 0.1


class _Job:
    """One request handed to the data path: run there once, or cancelled before it ran."""

    __slots__ = ("fn", "req", "resp", "out", "error", "done", "lock", "state")

    def __init__(self, fn: Callable[[Any, Any], Any], req: Any, resp: Any):
        self.fn, self.req, self.resp = fn, req, resp
        self.out: Any = None
        self.error: BaseException | None = None
        self.done = threading.Event()
        self.lock = threading.Lock()
        self.state = "waiting"  # -> "running" -> "done", or "cancelled"

    def run(self) -> None:
        with self.lock:
            if self.state != "waiting":
                return
            self.state = "running"
        try:
            self.out = self.fn(self.req, self.resp)
        except BaseException as exc:
            self.error = exc
            raise  # the data path fails as it would have with the service on it
        finally:
            self.state = "done"
            self.done.set()

    def cancel(self) -> bool:
        """True if it will never run (it had not started)."""
        with self.lock:
            if self.state == "waiting":
                self.state = "cancelled"
                return True
            return False


class ServiceUnavailable(RuntimeError):
    """The process stopped before the data path took the request (no answer is sent)."""


class ServiceSide:
    """The process's service thread (see the module notes)."""

    def __init__(self, nodes: list, executor, log: Callable[[str, str], None] | None = None):
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        self.nodes = nodes
        self.log = log or (lambda text, level: None)
        ctx = nodes[0].context
        self.node = rclpy.create_node(
            f"_fluxdrive_services_{os.getpid()}", context=ctx, start_parameter_services=False
        )
        self.jobs: deque[_Job] = deque()
        self.stopping = threading.Event()
        self.data_executor = executor
        self.moved: list[str] = []
        for n in nodes:
            self._move(n)
            n.service_side = self
        # jobs reach the data path through a steady-clock timer of its first node: rclpy's
        # EventsExecutor does not run a task created from another thread (create_task) until
        # something else wakes it, which on an idle node (the bench bridge between its CAN
        # thread's samples) is never
        from rclpy.clock import Clock, ClockType

        self.timer = nodes[0].create_timer(
            JOB_POLL_S, self.run_jobs, clock=Clock(clock_type=ClockType.STEADY_TIME)
        )
        self.executor = SingleThreadedExecutor(context=ctx)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, name="fluxdrive-services", daemon=True)
        self.thread.start()

    def _move(self, node) -> None:
        fqn = node.get_fully_qualified_name()
        for srv in list(node.services):
            name, srv_type, cb, qos = srv.service_name, srv.srv_type, srv.callback, srv.qos_profile
            kind = name.rsplit("/", 1)[-1]
            node.destroy_service(srv)
            if kind in READ_ONLY and name == f"{fqn}/{kind}":
                handler = cb
            else:
                handler = self._on_data_path(cb)
            self.node.create_service(srv_type, name, handler, qos_profile=qos)
            self.moved.append(name)

    def _on_data_path(self, cb: Callable[[Any, Any], Any]) -> Callable[[Any, Any], Any]:
        def handler(req: Any, resp: Any) -> Any:
            job = _Job(cb, req, resp)
            self.jobs.append(job)
            while not job.done.wait(POLL_S):
                if self.stopping.is_set() and job.cancel():
                    raise ServiceUnavailable("the process stopped before the request ran")
            if job.error is not None:
                raise ServiceUnavailable(f"the request failed: {job.error!r}")
            return job.out

        return handler

    def run_jobs(self) -> None:
        """The data path's side (its executor, between two callbacks): every waiting job."""
        while self.jobs:
            self.jobs.popleft().run()

    def _spin(self) -> None:
        self._raise_priority()
        while not self.stopping.is_set():
            try:
                self.executor.spin_once(timeout_sec=POLL_S)
            except ServiceUnavailable:
                continue  # no answer for this request; the client asks again or gives up
            except Exception:  # noqa: BLE001 - the context is shutting down
                if self.stopping.is_set() or not self.node.context.ok():
                    return
                raise

    def _raise_priority(self) -> None:
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), SERVICE_NICE)
        except (PermissionError, OSError, AttributeError) as exc:
            self.log(
                f"service thread at the process's priority: raising it to nice "
                f"{SERVICE_NICE} is not permitted here ({exc})",
                "info",
            )

    def close(self) -> None:
        """Stop the thread (requests still waiting for the data path get no answer) and
        remove the hidden node."""
        self.stopping.set()
        self.timer.cancel()
        self.thread.join(timeout=5.0)
        for job in list(self.jobs):
            job.cancel()
        try:
            self.executor.shutdown()
            self.node.destroy_node()
        except Exception:  # noqa: BLE001 - shutting down anyway
            pass
