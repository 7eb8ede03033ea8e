"""Services answered beside the data path: a process's service servers live on a thread of
their own, so a busy data path (a lockstep loop, a flood of samples) cannot leave a request
waiting in its queue.  The runner starts one per process (fluxdrive_ros.runner;
`FLUXDRIVE_SERVICE_THREAD=0` keeps the services on the data path's executor instead).

The runner opens one per process before it builds the nodes (`open_side`): every service
server its nodes (fluxdrive_ros.runner.FluxNode) create -- the six parameter services rclpy
gives each node, the controller's fault reset -- is created on a hidden node of the process
(`_fluxdrive_services_<pid>`, the same service names, so clients see no change;
`runner.FluxNode.create_service`), and once the nodes spin (`start`) a SingleThreadedExecutor
spins that node on a thread of its own, at a raised OS priority where the OS permits it (one
log line where it does not).  The servers are created there in the first place, not moved
when the process starts spinning: destroying a node's servers and creating them again on
the hidden node announced every service three times over discovery right when the process
started, and a client that had found a server as the node built it sent its requests to one
about to be destroyed.  Until `start` requests wait in DDS, as they waited
for the data path's executor to spin before.

What runs where, and why that is thread-safe
--------------------------------------------
- Reading parameters (`get_parameters`, `describe_parameters`, `list_parameters`,
  `get_parameter_types`) is answered on the service thread at once.  It reads the node's
  parameter and descriptor tables only: every fluxdrive node declares its parameters in its
  constructor, before this thread exists, so the tables never change size while it runs;
  a set replaces a table's entries (whole `Parameter` objects, each swap atomic under the
  GIL), never edits one in place.  A read takes `apply_lock`, which the data path holds
  while it applies a change, so a read never sees half of a set that changes several
  parameters at once: it sees all of them before or all after.
- Everything that changes a node (setting parameters, a fault reset) runs on the
  data path's thread, between two of its callbacks, exactly as when the data path's executor
  served it: the node's on-set callback rewrites the kernel's parameter row and the fault
  reset clears the kernel's latch on the only thread that runs the kernel, so a change
  never lands inside a sample and holds from the sample the node names
  (`applied from sample k`).  Nothing of the node's state is touched on the service thread.
- The service thread does not wait for a change: it queues the request as a job and goes
  on serving (reads, other requests); the data path runs the job at its next turn
  (a steady-clock timer of its first node, every JOB_POLL_S) and sends the answer itself.
  A request equal to one still waiting on the same service (a client asking again because
  the answer is late: `inspect.commands._call` re-sends after 1 s) is not queued a second
  time: it is answered with the first.  So a data path held up for seconds costs each
  change one wait, not one per re-sent copy in a line.

A node needs no change for any of this: the move is by the kind of service, see `READ_ONLY`.
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
# how often the data path looks for queued changes [s] (a steady-clock timer: rclpy's
# EventsExecutor does not run a task created from another thread until something else
# wakes it, which on an idle data path (no timer of its own, no message coming)
# is never)
JOB_POLL_S = 0.005
# the service thread's executor looks for its stop this often [s]
POLL_S = 0.1
# the environment variable that turns the service thread off ("0", "false", "no", "off")
ENV = "FLUXDRIVE_SERVICE_THREAD"


def wanted() -> bool:
    """The service thread is on unless FLUXDRIVE_SERVICE_THREAD says off."""
    return os.environ.get(ENV, "1").strip().lower() not in ("0", "false", "no", "off")


class _Job:
    """One change handed to the data path: run there once, then answered to every request
    it stands for (the first and any equal copy that came while it waited)."""

    __slots__ = ("service", "fn", "req", "resp", "out", "error", "lock", "state", "to")

    def __init__(self, service: str, fn: Callable[[Any, Any], Any], req: Any, resp: Any):
        self.service, self.fn, self.req, self.resp = service, fn, req, resp
        self.out: Any = None
        self.error: BaseException | None = None
        self.lock = threading.Lock()
        self.state = "waiting"  # -> "running" -> "done"
        # (send, header) of the requests still to be answered, once it is done
        self.to: list[tuple[Callable[[Any, Any], None], Any]] = []

    def run(self, apply_lock: threading.Lock) -> None:
        """On the data path's thread (its executor, between two callbacks)."""
        with self.lock:
            if self.state != "waiting":
                return
            self.state = "running"
        try:
            with apply_lock:
                self.out = self.fn(self.req, self.resp)
        except BaseException as exc:
            self.error = exc
            raise  # the data path fails as it would have with the service on it; no answer
        finally:
            with self.lock:
                self.state = "done"
                to, self.to = self.to, []
            self._answer(to)

    def answer_to(self, send: Callable[[Any, Any], None], header: Any) -> None:
        """Answer a request with this job's result: now if it is done, else when it is."""
        with self.lock:
            if self.state != "done":
                self.to.append((send, header))
                return
        self._answer([(send, header)])

    def _answer(self, to: list[tuple[Callable[[Any, Any], None], Any]]) -> None:
        if self.error is not None:
            return  # no answer, as rclpy sends none for a callback that raised
        for send, header in to:
            try:
                send(self.out, header)
            except Exception:  # noqa: BLE001 - the process is stopping: no answer
                pass


class ServiceSide:
    """The process's service node and thread (see the module notes)."""

    def __init__(self, context=None, log: Callable[[str, str], None] | None = None):
        import rclpy

        self.log = log or (lambda text, level: None)
        self.node = rclpy.create_node(
            f"_fluxdrive_services_{os.getpid()}",
            context=context,
            start_parameter_services=False,
            enable_rosout=False,
        )
        self.context = self.node.context
        self.jobs: deque[_Job] = deque()  # waiting for the data path, oldest first
        self.jobs_lock = threading.Lock()
        self.apply_lock = threading.Lock()  # held while a change is applied (module notes)
        # the job each deferred answer belongs to, by the response object the executor
        # hands to send_response
        self._deferred: dict[int, _Job] = {}
        self.stopping = threading.Event()
        self.served: list[str] = []  # the services created here
        self.n_jobs = 0  # changes run on the data path
        self.n_joined = 0  # requests answered with an equal one's job (re-sent copies)
        self.timer: Any = None
        self.executor: Any = None  # the service thread's (rclpy SingleThreadedExecutor)
        self.thread: threading.Thread | None = None

    def create_service(self, node, srv_type, name: str, callback, qos_profile):
        """A service server of `node` (its name resolved as the node resolves it: `~/x`,
        relative, remapped), created on the hidden node: a parameter read of the node itself
        answered on the service thread, anything else handed to the data path."""
        full = node.resolve_service_name(name)
        kind = full.rsplit("/", 1)[-1]
        if kind in READ_ONLY and full == f"{node.get_fully_qualified_name()}/{kind}":
            srv = self.node.create_service(
                srv_type, full, self._read(callback), qos_profile=qos_profile
            )
        else:
            srv = self.node.create_service(
                srv_type, full, self._on_data_path(full, callback), qos_profile=qos_profile
            )
            srv.send_response = self._send_deferred(srv.send_response)  # type: ignore[method-assign,assignment]
        self.served.append(full)
        return srv

    def start(self, nodes: list, executor) -> None:
        """The nodes spin on `executor` (the data path): changes run there from now on, and
        the service thread starts answering."""
        from rclpy.clock import Clock, ClockType
        from rclpy.executors import SingleThreadedExecutor

        for n in nodes:
            n.service_side = self
        self.log = nodes[0].log
        self.data_executor = executor
        self.timer = nodes[0].create_timer(
            JOB_POLL_S, self.run_jobs, clock=Clock(clock_type=ClockType.STEADY_TIME)
        )
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.thread = threading.Thread(target=self._spin, name="fluxdrive-services", daemon=True)
        self.thread.start()

    def _read(self, cb: Callable[[Any, Any], Any]) -> Callable[[Any, Any], Any]:
        def handler(req: Any, resp: Any) -> Any:
            with self.apply_lock:  # never half of a change (module notes)
                return cb(req, resp)

        return handler

    def _on_data_path(self, service: str, cb: Callable[[Any, Any], Any]):
        def handler(req: Any, resp: Any) -> Any:
            with self.jobs_lock:
                job = next(
                    (
                        j
                        for j in self.jobs
                        if j.service == service and j.state == "waiting" and j.req == req
                    ),
                    None,
                )
                if job is None:
                    job = _Job(service, cb, req, resp)
                    self.jobs.append(job)
                else:
                    self.n_joined += 1
                self._deferred[id(resp)] = job
            return resp  # answered by the job (send_response below), not now

        return handler

    def _send_deferred(self, send: Callable[[Any, Any], None]) -> Callable[[Any, Any], None]:
        """The service's send_response as its executor calls it right after the handler:
        the request's job answers it once it has run on the data path."""

        def deferred(response: Any, header: Any) -> None:
            with self.jobs_lock:
                job = self._deferred.pop(id(response), None)
            if job is None:
                send(response, header)
            else:
                job.answer_to(send, header)

        return deferred

    def run_jobs(self) -> None:
        """The data path's side (its executor, between two callbacks): every waiting job."""
        while True:
            with self.jobs_lock:
                if not self.jobs:
                    return
                job = self.jobs.popleft()
            self.n_jobs += 1
            job.run(self.apply_lock)

    def _spin(self) -> None:
        self._raise_priority()
        while not self.stopping.is_set():
            try:
                self.executor.spin_once(timeout_sec=POLL_S)
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
        """Stop the thread (changes still waiting for the data path get no answer: the
        process is stopping) and remove the hidden node with its services."""
        self.stopping.set()
        if self.timer is not None:
            self.timer.cancel()
        if self.thread is not None:
            self.thread.join(timeout=5.0)
        with self.jobs_lock:
            self.jobs.clear()
        _SIDES.pop(id(self.context), None)
        try:
            if self.executor is not None:
                self.executor.shutdown()
            self.node.destroy_node()
        except Exception:  # noqa: BLE001 - shutting down anyway
            pass


# the open service side of each context of this process (one: the runner's)
_SIDES: dict[int, ServiceSide] = {}


def open_side(context=None, log: Callable[[str, str], None] | None = None) -> ServiceSide | None:
    """The process's service side for `context` (the default context if None), opened now
    unless FLUXDRIVE_SERVICE_THREAD says off (then None).  The runner calls it before it
    builds the nodes, so that their services are created on it (fluxdrive_ros.runner)."""
    if not wanted():
        return None
    from rclpy.utilities import get_default_context

    ctx = context if context is not None else get_default_context()
    side = _SIDES.get(id(ctx))
    if side is None:
        side = _SIDES[id(ctx)] = ServiceSide(ctx, log)
    return side


def side_of(context) -> ServiceSide | None:
    """The open service side of `context`, if the process opened one (open_side)."""
    return _SIDES.get(id(context))
