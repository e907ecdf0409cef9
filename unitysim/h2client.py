"""A minimal blocking gRPC unary client over HTTP/2, for the player's one call per step.

A synchronous grpcio unary call costs the player 0.2-0.3 ms of CPU per exchange (C-core
plus its Python glue), as much as the trainer's whole share of a 3DBall step. The player
needs very little of gRPC: one method, one call in flight, loopback, plaintext, no
compression, no deadlines after the handshake. :class:`H2Channel` does exactly that over
a plain TCP socket: HTTP/2 framing, SETTINGS/PING/WINDOW_UPDATE/GOAWAY/RST_STREAM, flow
control both ways (requests of several MB wait for the server's window), and response
header blocks decoded with ``hpack`` (one decoder per connection, as HPACK state requires).
The frames, the request header block and a connection's state are in
:mod:`unitysim.h2connection`; this module makes the call on them.

It owns one connection at a time (reconnecting lazily after the server closed one) and
maps every failure to :class:`~unitysim.h2connection.RpcError`, a ``grpc.RpcError`` with
``code()``, so callers handle both clients alike. It does not do TLS, streaming calls,
concurrent calls, retries or proxies; the player keeps grpcio as a fallback
(``UNITYSIM_GRPC_CLIENT=grpcio``).
"""

from __future__ import annotations

import socket
import struct
import time
from urllib.parse import unquote

from unitysim.h2connection import (
    ACK,
    CONTINUATION,
    DATA,
    END_HEADERS,
    END_STREAM,
    FRAME_HEADER,
    GOAWAY,
    HEADERS,
    MAX_WINDOW,
    PADDED,
    PING,
    PRIORITY_FLAG,
    PUSH_PROMISE,
    RST_STREAM,
    SETTING,
    SETTINGS,
    SETTINGS_INITIAL_WINDOW,
    SETTINGS_MAX_FRAME,
    U32,
    WINDOW_UPDATE,
    Connection,
    RpcError,
    StatusCode,
    frame,
    request_headers,
)

_GRPC_PREFIX = struct.Struct(">BL")  # compressed flag, message length

_CODES = {code.value[0]: code for code in StatusCode}
# HTTP/2 error codes of RST_STREAM / GOAWAY to gRPC (gRPC's "HTTP/2 to gRPC" mapping).
_RST_CODES = {7: StatusCode.UNAVAILABLE, 8: StatusCode.CANCELLED, 11: StatusCode.RESOURCE_EXHAUSTED}
_RST_CODES[12] = StatusCode.PERMISSION_DENIED
_HTTP_CODES = {400: StatusCode.INTERNAL, 401: StatusCode.UNAUTHENTICATED}
_HTTP_CODES.update({403: StatusCode.PERMISSION_DENIED, 404: StatusCode.UNIMPLEMENTED})
_HTTP_CODES.update(dict.fromkeys((429, 502, 503, 504), StatusCode.UNAVAILABLE))


class _Call:
    """What one call has received so far."""

    __slots__ = ("data", "done", "headers", "reset", "send_window", "stream", "trailers", "unacked")

    def __init__(self, stream: int, send_window: int) -> None:
        self.stream = stream
        self.send_window = send_window
        self.headers: list[tuple[str, str]] | None = None
        self.trailers: list[tuple[str, str]] | None = None
        self.data: list[bytes] = []
        self.done = False  # the server ended its side of the stream
        self.reset: int | None = None  # RST_STREAM error code
        self.unacked = 0  # DATA bytes received since our last stream WINDOW_UPDATE


class H2Channel:
    """Unary gRPC calls to one method on ``host:port``, one at a time, over one connection."""

    def __init__(self, host: str, port: int, method: str) -> None:
        self.host = host
        self.port = port
        self.method = method
        self._headers = request_headers(method, f"{host}:{port}")
        self._connection: Connection | None = None

    def __enter__(self) -> H2Channel:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def close(self) -> None:
        if self._connection is not None:
            self._connection.close()
            self._connection = None

    def call(
        self, request: bytes, timeout: float | None = None, wait_for_ready: bool = False
    ) -> bytes:
        """Send ``request`` (a serialized message) and return the response message's bytes.

        ``timeout`` bounds the whole call, connecting included; ``wait_for_ready`` keeps
        trying to connect until then instead of failing at once (the trainer may still be
        starting its server). Raises :class:`RpcError` for every failure."""
        deadline = None if timeout is None else time.monotonic() + timeout
        connection = self._connection
        if connection is not None and connection.closing:
            self.close()  # as grpcio does, a new call after GOAWAY opens a new connection
            connection = None
        if connection is None:
            connection = self._connection = self._connect(deadline, wait_for_ready)
        elif deadline is not None:
            connection.sock.settimeout(max(deadline - time.monotonic(), 1e-3))
        try:
            return self._exchange(connection, request)
        except TimeoutError:
            self.close()
            raise RpcError(StatusCode.DEADLINE_EXCEEDED, "deadline exceeded") from None
        except OSError as error:
            self.close()
            raise RpcError(StatusCode.UNAVAILABLE, f"connection lost: {error}") from None
        except RpcError:
            if connection is self._connection and connection.closing:
                self.close()
            raise
        finally:
            if deadline is not None and self._connection is connection:
                connection.sock.settimeout(None)

    def _connect(self, deadline: float | None, wait_for_ready: bool) -> Connection:
        delay = 0.01
        while True:
            remaining = None if deadline is None else deadline - time.monotonic()
            if remaining is not None and remaining <= 0:
                raise RpcError(StatusCode.DEADLINE_EXCEEDED, "deadline exceeded while connecting")
            try:
                sock = socket.create_connection((self.host, self.port), timeout=remaining)
            except OSError as error:  # refused, unreachable, timed out
                if not wait_for_ready:
                    raise RpcError(StatusCode.UNAVAILABLE, f"cannot connect: {error}") from None
                pause = delay if remaining is None else min(delay, max(remaining, 0.0))
                time.sleep(pause)
                delay = min(2 * delay, 0.25)
                continue
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            sock.settimeout(remaining)
            try:
                return Connection(sock)
            except OSError as error:
                sock.close()
                raise RpcError(StatusCode.UNAVAILABLE, f"connection lost: {error}") from None

    def _exchange(self, connection: Connection, request: bytes) -> bytes:
        stream = connection.next_stream
        connection.next_stream += 2
        call = _Call(stream, connection.initial_window)
        head = frame(HEADERS, END_HEADERS, stream, self._headers)
        prefix = _GRPC_PREFIX.pack(0, len(request))
        size = len(request) + 5
        if size <= min(connection.max_frame, connection.send_window, call.send_window):
            # The usual case: the whole request in one write.
            connection.send_window -= size
            connection.sock.sendall(
                b"".join(
                    (
                        head,
                        FRAME_HEADER.pack(size >> 8, size & 0xFF, DATA, END_STREAM, stream),
                        prefix,
                        request,
                    )
                )
            )
        else:
            connection.sock.sendall(head)
            self._send_data(connection, call, prefix + request)
        while not call.done:
            self._handle(connection, call, *connection.read_frame())
        return self._result(connection, call)

    def _send_data(self, connection: Connection, call: _Call, body: bytes) -> None:
        """DATA frames within the server's frame size and flow-control windows; stops early
        when the server has answered or reset the stream (e.g. a message over its limit)."""
        view = memoryview(body)
        sent = 0
        while sent < len(body):
            if call.done or call.reset is not None:
                if call.reset is None:  # answered while we were sending: we are done
                    connection.sock.sendall(frame(RST_STREAM, 0, call.stream, U32.pack(0)))
                return
            size = min(
                len(body) - sent, connection.max_frame, connection.send_window, call.send_window
            )
            if size <= 0:
                self._handle(connection, call, *connection.read_frame())
                continue
            flags = END_STREAM if sent + size == len(body) else 0
            connection.sock.sendall(
                FRAME_HEADER.pack(size >> 8, size & 0xFF, DATA, flags, call.stream)
                + view[sent : sent + size]
            )
            connection.send_window -= size
            call.send_window -= size
            sent += size

    def _handle(
        self,
        connection: Connection,
        call: _Call,
        kind: int,
        flags: int,
        stream: int,
        payload: bytes,
    ) -> None:
        """Act on one frame from the server."""
        if kind == DATA:
            size = len(payload)
            if flags & PADDED:
                payload = payload[1 : size - payload[0]]
            if stream == call.stream:
                call.data.append(bytes(payload))
                call.unacked += size
                if flags & END_STREAM:
                    call.done = True
                elif call.unacked > MAX_WINDOW // 2:
                    connection.sock.sendall(frame(WINDOW_UPDATE, 0, stream, U32.pack(call.unacked)))
                    call.unacked = 0
            connection.unacked += size
            if connection.unacked > MAX_WINDOW // 2:
                connection.sock.sendall(frame(WINDOW_UPDATE, 0, 0, U32.pack(connection.unacked)))
                connection.unacked = 0
        elif kind == HEADERS:
            if flags & PADDED:
                payload = payload[1 : len(payload) - payload[0]]
            if flags & PRIORITY_FLAG:
                payload = payload[5:]
            block = bytes(payload)
            while not flags & END_HEADERS:
                kind2, flags2, _, more = connection.read_frame()
                if kind2 != CONTINUATION:
                    raise self._fail(connection, "expected a CONTINUATION frame")
                block += more
                flags = (flags & ~END_HEADERS) | (flags2 & END_HEADERS)
            headers = connection.decode_block(block)  # always: HPACK state is per connection
            if stream == call.stream:
                if call.headers is None and not call.data:
                    call.headers = headers
                else:
                    call.trailers = headers
                if flags & END_STREAM:
                    call.done = True
        elif kind == SETTINGS:
            if not flags & ACK:
                for offset in range(0, len(payload) - 5, 6):
                    key, value = SETTING.unpack_from(payload, offset)
                    if key == SETTINGS_INITIAL_WINDOW:
                        call.send_window += value - connection.initial_window
                        connection.initial_window = value
                    elif key == SETTINGS_MAX_FRAME:
                        connection.max_frame = value
                connection.sock.sendall(frame(SETTINGS, ACK, 0))
        elif kind == PING:
            if not flags & ACK:
                connection.sock.sendall(frame(PING, ACK, 0, bytes(payload)))
        elif kind == WINDOW_UPDATE:
            increment = U32.unpack_from(payload)[0] & 0x7FFFFFFF
            if stream == 0:
                connection.send_window += increment
            elif stream == call.stream:
                call.send_window += increment
        elif kind == RST_STREAM:
            if stream == call.stream:
                call.reset = U32.unpack_from(payload)[0]
                call.done = True
        elif kind == GOAWAY:
            last, error = struct.unpack_from(">LL", payload)
            connection.goaway = last & 0x7FFFFFFF
            connection.closing = True
            if call.stream > connection.goaway:
                code = StatusCode.UNAVAILABLE
                raise RpcError(code, f"the server is going away (HTTP/2 error {error})")
        elif kind in (PUSH_PROMISE, CONTINUATION):
            raise self._fail(connection, f"unexpected frame type {kind}")
        # PRIORITY and unknown frame types are ignored, as HTTP/2 requires.

    def _fail(self, connection: Connection, reason: str) -> RpcError:
        connection.closing = True
        return RpcError(StatusCode.INTERNAL, f"HTTP/2 protocol error: {reason}")

    def _result(self, connection: Connection, call: _Call) -> bytes:
        """The response message, or the call's status as an RpcError."""
        trailers = call.trailers if call.trailers is not None else call.headers or []
        fields = dict(trailers)
        status = fields.get("grpc-status")
        if status is None:
            if call.reset is not None:
                code = _RST_CODES.get(call.reset, StatusCode.INTERNAL)
                raise RpcError(code, f"stream reset by the server (HTTP/2 error {call.reset})")
            http = dict(call.headers or []).get(":status", "")
            if http != "200":
                code = _HTTP_CODES.get(int(http) if http.isdigit() else 0, StatusCode.UNKNOWN)
                raise RpcError(code, f"HTTP status {http or 'missing'}")
            raise RpcError(StatusCode.INTERNAL, "the server sent no grpc-status")
        if status != "0":
            code = _CODES.get(int(status) if status.isdigit() else -1, StatusCode.UNKNOWN)
            raise RpcError(code, unquote(fields.get("grpc-message", "")))
        data = call.data[0] if len(call.data) == 1 else b"".join(call.data)
        if len(data) < 5:
            raise RpcError(StatusCode.INTERNAL, "the response has no message")
        compressed, length = _GRPC_PREFIX.unpack_from(data)
        if compressed:
            raise RpcError(StatusCode.INTERNAL, "compressed response (none was accepted)")
        if length != len(data) - 5:
            raise RpcError(StatusCode.INTERNAL, "a unary response must hold exactly one message")
        return data[5:]
