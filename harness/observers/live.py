"""Live view of a run over Foxglove's WebSocket protocol (foxglove-sdk).

:class:`LiveServer` serves the channels of ``run.mcap`` (same topic names, schemas and
message bytes; see ``harness/observers/log.py``) to Foxglove while the run is going: open
Foxglove, choose *Open connection*, then ``ws://127.0.0.1:8765`` (the host and port
given here), and load ``layouts/densityloop.json`` or add a 3D panel for ``/fields/*``
and ``/swarm/positions`` and a Plot panel for ``/metrics`` (``docs/viewer.md``).

The server is a sink beside the MCAP writer, never in its path: it receives the bytes
that were written, copies them into foxglove-sdk's per-client queues (bounded; the
oldest message is dropped for a slow client) and returns. A channel nobody subscribes
to is skipped before any copy, so a run without clients pays one dictionary lookup and
one flag test per message (and one clock update per step). The server uses its own
:class:`foxglove.Context`, so it never sees channels of other code in the process and
other sinks never see its own.

Clock: the server advertises the ``time`` capability and broadcasts the simulated time
(integer ns from t = 0) whenever a message of a later time is published. A viewer then
runs on the run's clock, starting at the epoch; without the capability Foxglove Studio
1.x stamps live messages with its own wall clock. Studio 1.x stamps each live message
with the latest time it has received, and foxglove-sdk sends times and messages on two
queues drained in no fixed order, so a message can carry the time of a neighbouring
step (the next or the previous one at the pace of a run; more when the client lags).
Each message frame also carries the message's own simulated log time, as in
``run.mcap``.

Subprotocols: foxglove-sdk 0.30 accepts only ``foxglove.sdk.v1``, the protocol that
``foxglove.websocket.v1`` was renamed to (the same messages; the name is the only
difference). Clients that offer only the old name (Foxglove Studio 1.x, Lichtblick
before it added the new name, the ``@foxglove/ws-protocol`` client) would get HTTP
400, so the SDK's server listens on a loopback port of its own and
:class:`SubprotocolShim` listens on the given address: it rewrites the name in the
upgrade request and in the server's answer and relays every other byte unchanged.
"""

from __future__ import annotations

import errno
import re
import socket
import sys
import threading

import foxglove
from foxglove import Capability

from harness.observers.base import RunContext, Status
from harness.parameters import ParameterError, flag, integer, require
from harness.records import StepRecord

DEFAULT_HOST = "127.0.0.1"


DEFAULT_PORT = 8765


SUBPROTOCOL = "foxglove.sdk.v1"
"""The WebSocket subprotocol foxglove-sdk's server accepts."""


LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
"""The protocol's former name, the one older clients offer."""


def ws_url(host: str, port: int) -> str:
    """The WebSocket URL of ``host:port``: ``ws://127.0.0.1:8765``, ``ws://name:8765``, an
    IPv6 address in brackets (``ws://[::1]:8765``, a zone as ``%25``, RFC 6874).
    """
    if ":" in host:
        bare = host.removeprefix("[").removesuffix("]")
        address, percent, zone = bare.partition("%")
        return f"ws://[{address}{'%25' + zone if percent else ''}]:{port}"
    return f"ws://{host}:{port}"


class LiveServerError(RuntimeError):
    """The live server could not start (for example, its port is in use)."""


class SubprotocolShim:
    """A loopback relay in front of foxglove-sdk's server for clients that offer only
    :data:`LEGACY_SUBPROTOCOL`.

    Each connection: the HTTP upgrade request (at most :attr:`MAX_HEAD` bytes) is read;
    if its ``Sec-WebSocket-Protocol`` offers :data:`LEGACY_SUBPROTOCOL` and not
    :data:`SUBPROTOCOL`, the legacy name is replaced by the new one, and in the server's
    answer the accepted name is replaced back. The WebSocket key and accept headers do
    not involve the subprotocol, so the handshake stays valid. Every other byte, in
    both directions and for the whole connection, is relayed unchanged, by two threads
    per connection (blocking socket calls, which release the GIL). A client that offers
    the new name passes through untouched.

    Args:
        host: Address to listen on.
        port: TCP port (``0``: any free port; read :attr:`port`).
        upstream: ``(host, port)`` of the server relayed to.

    Raises:
        OSError: if ``host:port`` cannot be bound.
    """

    MAX_HEAD = 65536
    """Longest HTTP head (bytes) read from either side before relaying starts."""

    CHUNK = 65536
    """Bytes read per relay call."""

    def __init__(self, host: str, port: int, upstream: tuple[str, int]) -> None:
        self.upstream = upstream
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)[0]
        self._listener = socket.socket(family, kind, proto)
        try:
            self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._listener.bind(address)
            self._listener.listen(16)
        except OSError:
            self._listener.close()
            raise
        self.port: int = self._listener.getsockname()[1]
        self._lock = threading.Lock()
        self._sockets: set[socket.socket] = set()
        self._closed = False
        self._thread = threading.Thread(target=self._accept, name="live-shim", daemon=True)
        self._thread.start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self._listener.accept()
            except OSError:
                return  # closed
            threading.Thread(
                target=self._connect, args=(client,), name="live-shim-conn", daemon=True
            ).start()

    def _track(self, sock: socket.socket) -> bool:
        with self._lock:
            if self._closed:
                return False
            self._sockets.add(sock)
            return True

    def _connect(self, client: socket.socket) -> None:
        server = None
        try:
            if not self._track(client):
                return
            head, rest = read_head(client, self.MAX_HEAD)
            head, legacy = offer_new_name(head)
            server = socket.create_connection(self.upstream)
            if not self._track(server):
                return
            server.sendall(head + rest)
            answer, rest = read_head(server, self.MAX_HEAD)
            if legacy:
                answer = accept_old_name(answer)
            client.sendall(answer + rest)
        except (OSError, ValueError):
            self._drop(client, server)
            return
        down = threading.Thread(
            target=self._relay, args=(server, client), name="live-shim-down", daemon=True
        )
        down.start()
        self._relay(client, server)
        down.join()
        self._drop(client, server)

    def _relay(self, src: socket.socket, dst: socket.socket) -> None:
        """Copy ``src`` to ``dst`` until ``src`` ends (then half-close ``dst``, so the
        other direction can finish its closing handshake) or fails (then end both).
        """
        try:
            while data := src.recv(self.CHUNK):
                dst.sendall(data)
            dst.shutdown(socket.SHUT_WR)
        except OSError:
            self._drop(src, dst)

    def _drop(self, *socks: socket.socket | None) -> None:
        for sock in socks:
            if sock is None:
                continue
            with self._lock:
                self._sockets.discard(sock)
            try:
                sock.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass
            sock.close()

    def close(self) -> None:
        """Stop listening and end every relayed connection (idempotent)."""
        with self._lock:
            self._closed = True
            socks = list(self._sockets)
        try:
            self._listener.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass
        self._listener.close()
        self._drop(*socks)
        self._thread.join(1.0)


def read_head(sock: socket.socket, limit: int) -> tuple[bytes, bytes]:
    """An HTTP head read from ``sock`` up to and including its blank line, and the bytes
    read past it.

    Raises:
        ValueError: the peer closed first, or the head exceeds ``limit`` bytes.
    """
    buf = b""
    while (end := buf.find(b"\r\n\r\n")) < 0:
        if len(buf) > limit:
            raise ValueError("HTTP head too long")
        data = sock.recv(4096)
        if not data:
            raise ValueError("connection closed before the end of the HTTP head")
        buf += data
    return buf[: end + 4], buf[end + 4 :]


_PROTOCOL_HEADER = re.compile(rb"(?im)^(sec-websocket-protocol:)([^\r\n]*)")


def offer_new_name(request: bytes) -> tuple[bytes, bool]:
    """The upgrade request with :data:`LEGACY_SUBPROTOCOL` offered as
    :data:`SUBPROTOCOL`, and whether it was rewritten (not when the client offers the
    new name itself, or neither).
    """
    offers = [
        token.strip().decode("latin-1")
        for match in _PROTOCOL_HEADER.finditer(request)
        for token in match[2].split(b",")
    ]
    if SUBPROTOCOL in offers or LEGACY_SUBPROTOCOL not in offers:
        return request, False

    def rename(match: re.Match[bytes]) -> bytes:
        tokens = [t.strip() for t in match[2].split(b",")]
        new = [SUBPROTOCOL.encode() if t == LEGACY_SUBPROTOCOL.encode() else t for t in tokens]
        return match[1] + b" " + b", ".join(new)

    return _PROTOCOL_HEADER.sub(rename, request), True


def accept_old_name(answer: bytes) -> bytes:
    """The server's answer with the accepted :data:`SUBPROTOCOL` named
    :data:`LEGACY_SUBPROTOCOL`, the name the client offered.
    """
    return _PROTOCOL_HEADER.sub(
        lambda m: (
            m[1] + b" " + LEGACY_SUBPROTOCOL.encode()
            if m[2].strip() == SUBPROTOCOL.encode()
            else m[0]
        ),
        answer,
    )


class LiveServer:
    """A Foxglove WebSocket server for the topics of a run, on the simulated clock,
    reachable with either subprotocol name (see the module docstring).

    Args:
        host: Address to bind (``127.0.0.1``: this machine only).
        port: TCP port (``0``: any free port; read :attr:`port` afterwards).
        name: Server name shown in Foxglove.
        backlog: Messages queued per client before the oldest is dropped.

    Raises:
        LiveServerError: if the server cannot bind ``host:port``; the message is one
            line naming the address and the cause.
    """

    def __init__(
        self,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        name: str = "densityloop",
        backlog: int = 1024,
    ) -> None:
        self.host = host
        self._context = foxglove.Context()
        self._channels: dict[str, foxglove.Channel] = {}
        self._time_ns = -1  # the last time broadcast (ns of simulated time)
        try:
            self._server = foxglove.start_server(
                name=name,
                host="127.0.0.1",
                port=0,
                capabilities=[Capability.Time],
                context=self._context,
                message_backlog_size=backlog,
            )
        except RuntimeError as err:
            cause = str(err).removeprefix("FoxgloveError: ").strip()
            raise LiveServerError(f"live view: cannot start the server: {cause}") from None
        try:
            self._shim = SubprotocolShim(host, port, ("127.0.0.1", self._server.port))
        except OSError as err:
            self._server.stop()
            raise LiveServerError(
                f"live view: cannot serve on {ws_url(host, port)}: {err.strerror or err} "
                f"(choose another log.live_port or stop the program using it)"
            ) from None
        self.port: int = self._shim.port
        self._closed = False

    @property
    def url(self) -> str:
        """``ws://host:port``, the address to open in Foxglove (:func:`ws_url`)."""
        return ws_url(self.host, self.port)

    def channel(
        self,
        topic: str,
        schema_name: str,
        schema_encoding: str,
        schema_data: bytes,
        message_encoding: str,
    ) -> None:
        """Advertise ``topic`` to clients (idempotent: a known topic is left as it is).

        Args:
            topic: Topic name, as in ``run.mcap``.
            schema_name: Schema name (``foxglove.Grid``, ``densityloop.Metrics``, ...).
            schema_encoding: ``protobuf`` (a serialized FileDescriptorSet) or
                ``jsonschema``.
            schema_data: The schema record's bytes, as in ``run.mcap``.
            message_encoding: ``protobuf`` or ``json``.
        """
        if self._closed or topic in self._channels:
            return
        schema = foxglove.Schema(name=schema_name, encoding=schema_encoding, data=schema_data)
        self._channels[topic] = foxglove.Channel(
            topic, schema=schema, message_encoding=message_encoding, context=self._context
        )

    def subscribed(self, topic: str) -> bool:
        """Whether a client currently subscribes to ``topic``."""
        ch = self._channels.get(topic)
        return ch is not None and not self._closed and ch.has_sinks()

    def publish(self, topic: str, log_time_ns: int, data: bytes) -> None:
        """Send one message to the clients subscribed to ``topic``; never blocks. A
        time later than any before is first broadcast as the server's clock.

        Args:
            topic: An advertised topic (see :meth:`channel`); others are ignored.
            log_time_ns: Message time (integer ns of simulated time).
            data: The serialized message, byte for byte as written to the log.
        """
        if self._closed:
            return
        if log_time_ns > self._time_ns:
            self._time_ns = log_time_ns
            self._server.broadcast_time(log_time_ns)
        ch = self._channels.get(topic)
        if ch is None or not ch.has_sinks():
            return
        ch.log(data, log_time=log_time_ns)

    STOP_S = 2.0
    """Longest wait (s) for the server to stop: a client that subscribed and stopped
    reading would hold it for its queue's flush (tens of seconds)."""

    def close(self) -> None:
        """Unadvertise every channel and stop the server (idempotent), waiting at most
        :attr:`STOP_S` for it (in a daemon thread, so signals stay handled and the
        process can end while a stalled client holds the server).
        """
        if self._closed:
            return
        self._closed = True
        for ch in self._channels.values():
            ch.close()
        stopper = threading.Thread(target=self._server.stop, name="live-stop", daemon=True)
        stopper.start()
        stopper.join(self.STOP_S)
        self._shim.close()
        if stopper.is_alive():
            print(
                f"live view: a client of {self.url} is not reading; not waiting for it",
                file=sys.stderr,
            )

    def __enter__(self) -> LiveServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class LiveView:
    """The observer ``live``: serves every message the log writes while the run goes.

    Args:
        enabled: Serve (``log.live``); off, the observer does nothing.
        host: Address to bind (``log.live_host``).
        port: TCP port, 0 to 65535 (``log.live_port``; 0: any free port).

    :meth:`initialize` starts the server and adds it to the run's publishers, which the
    logger (after this observer) hands every message; a port that cannot be served is a
    refused ``port`` (:class:`~harness.parameters.ParameterError`), raised before the log
    exists.
    """

    def __init__(self, enabled: bool = False, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT):
        self.enabled = flag("enabled", enabled)
        self.port = integer("port", port, 0)
        require(self.port <= 65535, "port", port, "a TCP port, 0 to 65535 (0: any free port)")
        require(isinstance(host, str) and bool(host), "host", host, "an address such as 127.0.0.1")
        self.host = host
        self.server: LiveServer | None = None

    def probe(self) -> None:
        """Check, before anything is written, that the server could start: the host
        resolves to an address of this machine and the port is free (when not 0).

        Raises:
            ParameterError: ``host`` for an address that does not resolve or is not this
                machine's, ``port`` for a port in use or not allowed.
        """
        if not self.enabled:
            return
        try:
            infos = socket.getaddrinfo(self.host, self.port, type=socket.SOCK_STREAM)
        except (OSError, UnicodeError) as err:
            raise ParameterError(
                "host", self.host, f"an address of this machine to serve on ({err})"
            ) from None
        family, kind, proto, _, address = infos[0]
        with socket.socket(family, kind, proto) as s:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                s.bind(address)
            except OSError as err:
                if err.errno in (errno.EADDRINUSE, errno.EACCES):
                    raise ParameterError(
                        "port",
                        self.port,
                        f"a port free to serve on ({ws_url(self.host, self.port)}: "
                        f"{err.strerror}; choose another log.live_port or stop the program "
                        "using it)",
                    ) from None
                raise ParameterError(
                    "host", self.host, f"an address of this machine to serve on ({err.strerror})"
                ) from None

    def initialize(self, run: RunContext) -> None:
        """Start the server (when enabled) and say where it is, on standard error."""
        if not self.enabled:
            return
        self.probe()
        try:
            self.server = LiveServer(self.host, self.port)
        except LiveServerError as err:
            raise ParameterError("port", self.port, str(err)) from None
        run.publishers.append(self.server)
        print(f"live view: {self.server.url} (Foxglove: Open connection)", file=sys.stderr)

    def handle(self, rec: StepRecord, values: dict[str, float | None]) -> None:
        """Nothing: the logger publishes."""

    def finalize(self, status: Status) -> None:
        """Stop the server."""
        if self.server is not None:
            self.server.close()
