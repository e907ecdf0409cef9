"""The Python end of the Unity connection: mlagents' gRPC server, bound to 127.0.0.1 only
and without SO_REUSEPORT (a second server on a port fails loudly instead of splitting the
traffic), handing messages between the gRPC thread and the worker through in-process
queues instead of mlagents' pickling Pipe, and checking the player process often while
it waits for an answer."""

from __future__ import annotations

import queue
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import grpc
from mlagents_envs.communicator_objects.unity_to_external_pb2_grpc import (
    add_UnityToExternalProtoServicer_to_server,
)
from mlagents_envs.exception import UnityTimeOutException, UnityWorkerInUseException
from mlagents_envs.rpc_communicator import (
    RpcCommunicator,
    UnityToExternalServicerImplementation,
)

PROCESS_POLL_S = 0.2  # how often a wait for Unity's answer checks that the player lives


_CLOSED = object()


class _ThreadPipe:
    """The end of a two-way, in-process channel with the API mlagents uses of a
    ``multiprocessing`` Connection (send / recv / poll / close), minus the pickling and
    the syscalls: both ends live in one process (the gRPC handler thread and ours)."""

    def __init__(self, inbox: queue.SimpleQueue, outbox: queue.SimpleQueue) -> None:
        self._inbox, self._outbox = inbox, outbox
        self._stash: list[object] = []

    def send(self, message: object) -> None:
        self._outbox.put(message)

    def poll(self, timeout: float = 0.0) -> bool:
        if not self._stash:
            try:
                self._stash.append(
                    self._inbox.get(timeout=timeout) if timeout else self._inbox.get_nowait()
                )
            except queue.Empty:
                return False
        return True

    def recv(self) -> object:
        message = self._stash.pop() if self._stash else self._inbox.get()
        if message is _CLOSED:
            self._inbox.put(_CLOSED)  # wake any other reader too
            raise EOFError("the other end closed the channel")
        return message

    def close(self) -> None:
        self._outbox.put(_CLOSED)


class _ThreadedServicer(UnityToExternalServicerImplementation):
    """mlagents' servicer with the multiprocessing Pipe replaced by in-process queues."""

    def __init__(self) -> None:  # no super().__init__(): it would open a Pipe
        to_python: queue.SimpleQueue = queue.SimpleQueue()
        to_unity: queue.SimpleQueue = queue.SimpleQueue()
        self.parent_conn = _ThreadPipe(inbox=to_python, outbox=to_unity)
        self.child_conn = _ThreadPipe(inbox=to_unity, outbox=to_python)


class LoopbackCommunicator(RpcCommunicator):
    """mlagents' server, but on 127.0.0.1 only and without SO_REUSEPORT, so a second
    server on the same port fails loudly instead of splitting the traffic; the gRPC
    thread hands messages over through in-process queues instead of a pickling Pipe."""

    def __init__(self, port: int, timeout_wait: int, on_bound: Callable[[int], None]) -> None:
        self._on_bound = on_bound
        super().__init__(worker_id=0, base_port=port, timeout_wait=timeout_wait)

    def create_server(self) -> None:
        server = grpc.server(
            thread_pool=ThreadPoolExecutor(max_workers=10),
            options=(("grpc.so_reuseport", 0),),
        )
        self.unity_to_external = _ThreadedServicer()
        add_UnityToExternalProtoServicer_to_server(self.unity_to_external, server)
        try:
            bound = server.add_insecure_port(f"127.0.0.1:{self.port}")
        except RuntimeError:
            bound = 0
        if bound != self.port:
            server.stop(None)
            raise UnityWorkerInUseException(self.worker_id)
        server.start()
        self.server = server
        self.is_open = True
        self._on_bound(self.port)

    def poll_for_timeout(self, poll_callback: Callable[[], None] | None = None) -> None:
        """mlagents' wait for Unity's answer (``UnityTimeOutException`` after
        ``timeout_wait``), but checking the player process every 0.2 s instead of every
        ``timeout_wait / 10`` (6 s): a crashed player is found at once, not 6 s later."""
        deadline = time.monotonic() + self.timeout_wait
        while time.monotonic() < deadline:
            if self.unity_to_external.parent_conn.poll(PROCESS_POLL_S):
                return
            if poll_callback is not None:
                poll_callback()  # raises once the player has exited
        raise UnityTimeOutException(
            f"Unity did not answer within timeout_wait ({self.timeout_wait} s): it hangs, or "
            "needs more time to start (a larger timeout_wait)"
        )
