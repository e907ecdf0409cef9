"""A minimal blocking gRPC unary client over HTTP/2, for the player's one call per step.

A synchronous grpcio unary call costs the player 0.2-0.3 ms of CPU per exchange (C-core
plus its Python glue), as much as the trainer's whole share of a 3DBall step. The player
needs very little of gRPC: one method, one call in flight, loopback, plaintext, no
compression, no deadlines after the handshake. :class:`H2Channel` does exactly that over
a plain TCP socket: HTTP/2 framing, SETTINGS/PING/WINDOW_UPDATE/GOAWAY/RST_STREAM, flow
control both ways (requests of several MB wait for the server's window), and response
header blocks decoded with ``hpack`` (one decoder per connection, as HPACK state requires).

It owns one connection at a time (reconnecting lazily after the server closed one) and
maps every failure to :class:`RpcError`, a ``grpc.RpcError`` with ``code()``, so callers
handle both clients alike. It does not do TLS, streaming calls, concurrent calls, retries
or proxies; the player keeps grpcio as a fallback (``UNITYSIM_GRPC_CLIENT=grpcio``).
"""

from __future__ import annotations

import contextlib
import socket
import struct
import time
from urllib.parse import unquote

import grpc
import hpack

PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n"
MAX_WINDOW = 2**31 - 1
MAX_FRAME = 2**24 - 1
DEFAULT_WINDOW = 65535
DEFAULT_FRAME = 16384

# Frame types and flags (RFC 9113 §6).
DATA, HEADERS, PRIORITY, RST_STREAM, SETTINGS, PUSH_PROMISE, PING, GOAWAY = range(8)
WINDOW_UPDATE, CONTINUATION = 8, 9
END_STREAM, ACK, END_HEADERS, PADDED, PRIORITY_FLAG = 0x1, 0x1, 0x4, 0x8, 0x20
SETTINGS_ENABLE_PUSH, SETTINGS_INITIAL_WINDOW, SETTINGS_MAX_FRAME = 2, 4, 5

_FRAME = struct.Struct(">HBBBL")  # 24-bit length as 16 + 8 bits, type, flags, stream id
_U32 = struct.Struct(">L")
_SETTING = struct.Struct(">HL")
_GRPC_PREFIX = struct.Struct(">BL")  # compressed flag, message length

StatusCode = grpc.StatusCode
_CODES = {code.value[0]: code for code in StatusCode}
# HTTP/2 error codes of RST_STREAM / GOAWAY to gRPC (gRPC's "HTTP/2 to gRPC" mapping).
_RST_CODES = {7: StatusCode.UNAVAILABLE, 8: StatusCode.CANCELLED, 11: StatusCode.RESOURCE_EXHAUSTED}
_RST_CODES[12] = StatusCode.PERMISSION_DENIED
_HTTP_CODES = {400: StatusCode.INTERNAL, 401: StatusCode.UNAUTHENTICATED}
_HTTP_CODES.update({403: StatusCode.PERMISSION_DENIED, 404: StatusCode.UNIMPLEMENTED})
_HTTP_CODES.update(dict.fromkeys((429, 502, 503, 504), StatusCode.UNAVAILABLE))


class RpcError(grpc.RpcError):
    """A failed call: ``code()`` is a ``grpc.StatusCode``, as grpcio's errors have."""

    def __init__(self, code: grpc.StatusCode, details: str = "") -> None:
        super().__init__(f"{code.name}: {details}" if details else code.name)
        self._code = code
        self._details = details

    def code(self) -> grpc.StatusCode:
        return self._code

    def details(self) -> str:
        return self._details


def frame(kind: int, flags: int, stream: int, payload: bytes = b"") -> bytes:
    """One HTTP/2 frame: 9-byte header, then the payload."""
    size = len(payload)
    return _FRAME.pack(size >> 8, size & 0xFF, kind, flags, stream) + payload


def _literal(name: str, value: str) -> bytes:
    """HPACK literal header field without indexing, new name (RFC 7541 §6.2.2), no Huffman."""
    out = b"\x00"
    for text in (name.encode(), value.encode()):
        if len(text) >= 127:
            raise ValueError("header too long for a one-byte HPACK length")
        out += bytes((len(text),)) + text
    return out


def request_headers(method: str, authority: str) -> bytes:
    """The header block of every call, encoded once: it never touches HPACK's dynamic table."""
    fields = (
        (":method", "POST"),
        (":scheme", "http"),
        (":path", method),
        (":authority", authority),
        ("content-type", "application/grpc"),
        ("te", "trailers"),
    )
    return b"".join(_literal(name, value) for name, value in fields)


class _Connection:
    """One HTTP/2 connection: a socket, its read buffer, flow-control windows, HPACK state."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.buffer = bytearray()
        self.pos = 0
        self.decoder = hpack.Decoder()
        self.decoded: dict[bytes, list[tuple[str, str]]] = {}  # see decode_block
        self.table_size = 0
        self.table_first: object = None
        self.send_window = DEFAULT_WINDOW  # connection level, ours towards the server
        self.initial_window = DEFAULT_WINDOW  # the server's SETTINGS_INITIAL_WINDOW_SIZE
        self.max_frame = DEFAULT_FRAME  # the server's SETTINGS_MAX_FRAME_SIZE
        self.unacked = 0  # DATA bytes received since our last connection WINDOW_UPDATE
        self.next_stream = 1
        self.goaway: int | None = None  # the server's last stream id once it sent GOAWAY
        self.closing = False  # GOAWAY, end of stream or a protocol error: no new calls
        settings = b"".join(
            _SETTING.pack(key, value)
            for key, value in (
                (SETTINGS_ENABLE_PUSH, 0),
                (SETTINGS_INITIAL_WINDOW, MAX_WINDOW),
                (SETTINGS_MAX_FRAME, MAX_FRAME),
            )
        )
        sock.sendall(
            PREFACE
            + frame(SETTINGS, 0, 0, settings)
            + frame(WINDOW_UPDATE, 0, 0, _U32.pack(MAX_WINDOW - DEFAULT_WINDOW))
        )

    def close(self) -> None:
        with contextlib.suppress(OSError):
            self.sock.close()

    def read_frame(self) -> tuple[int, int, int, bytes]:
        """The next frame: (type, flags, stream id, payload); blocks until it is complete.

        The payload is a copy: the buffer is compacted later, which no view may outlive."""
        buffer, pos = self.buffer, self.pos
        if len(buffer) - pos < 9:
            self._fill(9)
            buffer, pos = self.buffer, self.pos
        high, low, kind, flags, stream = _FRAME.unpack_from(buffer, pos)
        end = pos + 9 + (high << 8 | low)
        if len(buffer) < end:
            self._fill(end - pos)
            buffer, pos = self.buffer, self.pos
            end = pos + 9 + (high << 8 | low)
        self.pos = end
        with memoryview(buffer) as view:
            payload = view[pos + 9 : end].tobytes()
        return kind, flags, stream & 0x7FFFFFFF, payload

    def _fill(self, needed: int) -> None:
        """Read until ``needed`` bytes from ``pos`` are buffered (consumed bytes dropped)."""
        if self.pos:
            del self.buffer[: self.pos]
            self.pos = 0
        buffer = self.buffer
        while len(buffer) < needed:
            chunk = self.sock.recv(max(needed - len(buffer), 262144))
            if not chunk:
                self.closing = True
                raise RpcError(StatusCode.UNAVAILABLE, "the server closed the connection")
            buffer += chunk

    def decode_block(self, block: bytes) -> list[tuple[str, str]]:
        """Decode a header block (all of them: HPACK state is per connection).

        gRPC servers send the same few blocks on every call, mostly indexed fields, which
        hpack decodes at ~10 µs each. A block whose decoding left the dynamic table as it
        was is remembered, and reused while the table stays unchanged (the same entries:
        an insertion puts a new object first, an eviction shortens it)."""
        entries = self.decoder.header_table.dynamic_entries
        first = entries[0] if entries else None
        if len(entries) != self.table_size or first is not self.table_first:
            self.decoded.clear()
            self.table_size, self.table_first = len(entries), first
        cached = self.decoded.get(block)
        if cached is not None:
            return cached
        headers = [(str(name), str(value)) for name, value in self.decoder.decode(block, raw=False)]
        first = entries[0] if entries else None
        unchanged = len(entries) == self.table_size and first is self.table_first
        if unchanged and len(self.decoded) < 64:
            self.decoded[block] = headers
        return headers


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
        self._connection: _Connection | None = None

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

    def _connect(self, deadline: float | None, wait_for_ready: bool) -> _Connection:
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
                return _Connection(sock)
            except OSError as error:
                sock.close()
                raise RpcError(StatusCode.UNAVAILABLE, f"connection lost: {error}") from None

    def _exchange(self, connection: _Connection, request: bytes) -> bytes:
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
                        _FRAME.pack(size >> 8, size & 0xFF, DATA, END_STREAM, stream),
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

    def _send_data(self, connection: _Connection, call: _Call, body: bytes) -> None:
        """DATA frames within the server's frame size and flow-control windows; stops early
        when the server has answered or reset the stream (e.g. a message over its limit)."""
        view = memoryview(body)
        sent = 0
        while sent < len(body):
            if call.done or call.reset is not None:
                if call.reset is None:  # answered while we were sending: we are done
                    connection.sock.sendall(frame(RST_STREAM, 0, call.stream, _U32.pack(0)))
                return
            size = min(
                len(body) - sent, connection.max_frame, connection.send_window, call.send_window
            )
            if size <= 0:
                self._handle(connection, call, *connection.read_frame())
                continue
            flags = END_STREAM if sent + size == len(body) else 0
            connection.sock.sendall(
                _FRAME.pack(size >> 8, size & 0xFF, DATA, flags, call.stream)
                + view[sent : sent + size]
            )
            connection.send_window -= size
            call.send_window -= size
            sent += size

    def _handle(
        self,
        connection: _Connection,
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
                    connection.sock.sendall(
                        frame(WINDOW_UPDATE, 0, stream, _U32.pack(call.unacked))
                    )
                    call.unacked = 0
            connection.unacked += size
            if connection.unacked > MAX_WINDOW // 2:
                connection.sock.sendall(frame(WINDOW_UPDATE, 0, 0, _U32.pack(connection.unacked)))
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
                    key, value = _SETTING.unpack_from(payload, offset)
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
            increment = _U32.unpack_from(payload)[0] & 0x7FFFFFFF
            if stream == 0:
                connection.send_window += increment
            elif stream == call.stream:
                call.send_window += increment
        elif kind == RST_STREAM:
            if stream == call.stream:
                call.reset = _U32.unpack_from(payload)[0]
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

    def _fail(self, connection: _Connection, reason: str) -> RpcError:
        connection.closing = True
        return RpcError(StatusCode.INTERNAL, f"HTTP/2 protocol error: {reason}")

    def _result(self, connection: _Connection, call: _Call) -> bytes:
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
