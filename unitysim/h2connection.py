"""The HTTP/2 layer under :mod:`unitysim.h2client`: frames, request headers, connections.

Why a module of its own: HTTP/2 framing (RFC 9113) and HPACK sit below the gRPC call and
know nothing of it. Here are the frame types, flags and settings, :func:`frame`, the
request header block (encoded once: literal fields that never touch HPACK's dynamic
table) and :class:`Connection`, one connection's state: its socket and read buffer, the
flow-control windows and the HPACK decoder (one per connection, as HPACK state requires),
opened with our SETTINGS (no push, the largest windows and frames). :class:`RpcError`
lives here too, since a connection the server closed fails as one.
"""

from __future__ import annotations

import contextlib
import socket
import struct

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

FRAME_HEADER = struct.Struct(">HBBBL")  # 24-bit length as 16 + 8 bits, type, flags, stream id
U32 = struct.Struct(">L")
SETTING = struct.Struct(">HL")

StatusCode = grpc.StatusCode


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
    return FRAME_HEADER.pack(size >> 8, size & 0xFF, kind, flags, stream) + payload


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


class Connection:
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
            SETTING.pack(key, value)
            for key, value in (
                (SETTINGS_ENABLE_PUSH, 0),
                (SETTINGS_INITIAL_WINDOW, MAX_WINDOW),
                (SETTINGS_MAX_FRAME, MAX_FRAME),
            )
        )
        sock.sendall(
            PREFACE
            + frame(SETTINGS, 0, 0, settings)
            + frame(WINDOW_UPDATE, 0, 0, U32.pack(MAX_WINDOW - DEFAULT_WINDOW))
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
        high, low, kind, flags, stream = FRAME_HEADER.unpack_from(buffer, pos)
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
