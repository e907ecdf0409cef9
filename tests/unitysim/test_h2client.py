"""unitysim.h2client against a real grpcio server: round trips small and multi-MB, status
codes, waiting for a server that is not listening yet, a server that goes away, and no
socket or thread left behind; then whole sessions through the real UnityEnvironment with
each of the player's two clients."""

from __future__ import annotations

import hashlib
import os
import socket
import threading
import time
from collections.abc import Iterator
from concurrent import futures

import grpc
import psutil
import pytest
from mlagents_envs.exception import UnityEnvironmentException

from tests.helpers import free_port
from tests.waiting import wait_for
from unitysim.h2client import H2Channel
from unitysim.h2connection import RpcError
from unitysim.player import CLIENTS, EXCHANGE

SERVICE, METHOD = EXCHANGE[1:].split("/")
MB = 1024 * 1024
BALL = "3DBall?team=0"


def _handler(request: bytes, context: grpc.ServicerContext) -> bytes:
    """Echo reversed; ``abort:N`` ends with status N; ``big:N`` answers N bytes;
    ``wait:S`` answers after S seconds."""
    if request.startswith(b"abort:"):
        context.abort(grpc.StatusCode(_CODE[int(request[6:])]), "refused: 100% ü")
    if request.startswith(b"big:"):
        size = int(request[4:])
        return (hashlib.sha256(request).digest() * (size // 32 + 1))[:size]
    if request.startswith(b"wait:"):
        time.sleep(float(request[5:]))  # the slow answer itself, not a wait
    return request[::-1]


_CODE = {code.value[0]: code.value for code in grpc.StatusCode}


def start_server(port: int = 0) -> tuple[grpc.Server, int]:
    """A grpcio server like the trainer's: default 4 MiB receive limit, loopback only."""
    server = grpc.server(futures.ThreadPoolExecutor(4), options=[("grpc.so_reuseport", 0)])
    handler = grpc.unary_unary_rpc_method_handler(_handler)
    server.add_generic_rpc_handlers(
        (grpc.method_handlers_generic_handler(SERVICE, {METHOD: handler}),)
    )
    port = server.add_insecure_port(f"127.0.0.1:{port}")
    server.start()
    return server, port


@pytest.fixture
def server() -> Iterator[int]:
    grpc_server, port = start_server()
    yield port
    grpc_server.stop(None)


def _open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


def _client_sockets(port: int) -> int:
    """Our sockets connected to ``port`` (the in-test server's own ends not counted)."""
    connections = psutil.Process().net_connections("tcp")
    return sum(1 for c in connections if c.raddr and c.raddr.port == port)


def test_small_round_trips_reuse_one_connection(server):
    with H2Channel("localhost", server, EXCHANGE) as channel:
        assert channel.call(b"hello", timeout=5, wait_for_ready=True) == b"olleh"
        for i in range(50):
            payload = f"message {i}".encode()
            assert channel.call(payload) == payload[::-1]
        assert channel.call(b"") == b""
        assert _client_sockets(server) == 1  # one connection for all calls
    assert _client_sockets(server) == 0


def test_multi_megabyte_messages_both_ways(server):
    """Over the 65,535-byte initial windows and the 16,384-byte frame size, both ways."""
    with H2Channel("localhost", server, EXCHANGE) as channel:
        request = os.urandom(3 * MB)
        assert channel.call(request) == request[::-1]
        big = b"big:" + str(9 * MB).encode()
        answer = channel.call(big)
        assert answer == _handler(big, None)  # type: ignore[arg-type]
        assert len(answer) == 9 * MB
        assert channel.call(b"again") == b"niaga"


@pytest.mark.parametrize(
    "code", [grpc.StatusCode.RESOURCE_EXHAUSTED, grpc.StatusCode.NOT_FOUND], ids=str
)
def test_error_status_is_raised_with_its_code(server, code):
    with H2Channel("localhost", server, EXCHANGE) as channel:
        with pytest.raises(grpc.RpcError) as raised:
            channel.call(b"abort:%d" % code.value[0])
        assert raised.value.code() == code
        assert raised.value.details() == "refused: 100% ü"
        assert channel.call(b"ok") == b"ko"  # the connection survives an error status


def test_message_over_the_servers_limit_is_resource_exhausted(server):
    """The oversize fault: the trainer's server refuses more than 4 MiB while we send."""
    with H2Channel("localhost", server, EXCHANGE) as channel:
        with pytest.raises(RpcError) as raised:
            channel.call(b"x" * (4 * MB + 64 * 1024))
        assert raised.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert "larger than max" in raised.value.details()
        assert channel.call(b"still here") == b"ereh llits"


def test_waits_for_a_server_that_starts_later():
    port = free_port()
    started: list[grpc.Server] = []
    timer = threading.Timer(0.5, lambda: started.append(start_server(port)[0]))
    timer.start()
    try:
        with H2Channel("localhost", port, EXCHANGE) as channel:
            alone = not started  # no server yet as the call is made (most often)
            begin = time.monotonic()
            assert channel.call(b"late", timeout=60, wait_for_ready=True) == b"etal"
            assert started and (not alone or time.monotonic() - begin > 0.3)
    finally:
        timer.join()
        for grpc_server in started:
            grpc_server.stop(None)


def test_no_server_fails_at_once_or_at_the_deadline():
    port = free_port()
    with H2Channel("localhost", port, EXCHANGE) as channel:
        with pytest.raises(RpcError) as raised:
            channel.call(b"x")
        assert raised.value.code() == grpc.StatusCode.UNAVAILABLE
        begin = time.monotonic()
        with pytest.raises(RpcError) as raised:
            channel.call(b"x", timeout=0.5, wait_for_ready=True)
        assert raised.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
        assert time.monotonic() - begin > 0.4  # it waited (the code says it ended by then)


def test_deadline_covers_a_slow_answer(server):
    with H2Channel("localhost", server, EXCHANGE) as channel:
        with pytest.raises(RpcError) as raised:
            channel.call(b"wait:2", timeout=0.3)
        assert raised.value.code() == grpc.StatusCode.DEADLINE_EXCEEDED
        assert channel.call(b"wait:0.1") == b"1.0:tiaw"  # a fresh connection, no deadline


def test_server_going_away_is_unavailable_and_leaves_nothing_behind():
    fds, threads = _open_fds(), threading.active_count()
    grpc_server, port = start_server()
    channel = H2Channel("localhost", port, EXCHANGE)
    assert channel.call(b"ab") == b"ba"
    stopper = threading.Timer(0.3, lambda: grpc_server.stop(None))
    stopper.start()
    with pytest.raises(RpcError) as raised:
        channel.call(b"wait:3")  # in flight when the server stops
    stopper.join()
    assert raised.value.code() in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.CANCELLED)
    with pytest.raises(RpcError) as raised:
        channel.call(b"again")
    assert raised.value.code() == grpc.StatusCode.UNAVAILABLE
    channel.close()
    left = lambda: (_open_fds(), threading.active_count()) <= (fds, threads)  # noqa: E731
    wait_for(left, "a socket or thread left behind to close", 30)


def test_a_peer_that_closes_at_once_is_unavailable():
    """Not an HTTP/2 server at all: it accepts and hangs up."""
    with socket.create_server(("127.0.0.1", 0)) as listener:
        port = listener.getsockname()[1]

        def serve() -> None:
            connection, _ = listener.accept()
            connection.close()

        thread = threading.Thread(target=serve)
        thread.start()
        with H2Channel("localhost", port, EXCHANGE) as channel, pytest.raises(RpcError) as raised:
            channel.call(b"x", timeout=5, wait_for_ready=True)
        thread.join()
    assert raised.value.code() == grpc.StatusCode.UNAVAILABLE


@pytest.mark.integration
@pytest.mark.parametrize("client", CLIENTS)
def test_session_with_each_client(open_env, client):
    with open_env("3DBall", seed=3, additional_args=["--grpc-client", client]) as env:
        env.reset()
        for _ in range(20):
            env.step()
        decisions, _ = env.get_steps(BALL)
        assert len(decisions) == 12


@pytest.mark.integration
@pytest.mark.parametrize("client", CLIENTS)
def test_oversize_fault_with_each_client(open_env, client):
    flags = ["--grpc-client", client, "--sim-oversize-after", "2"]
    with (
        open_env("3DBall", additional_args=flags) as env,
        pytest.raises(UnityEnvironmentException, match="return code 1"),
    ):
        env.reset()
        for _ in range(5):
            env.step()
