"""Live view of a run over Foxglove's WebSocket protocol (foxglove-sdk).

:class:`LiveServer` serves the channels of ``run.mcap`` (same topic names, schemas and
message bytes; see ``harness/mcap_log.py``) to Foxglove while the run is going: open
Foxglove, choose *Open connection*, then ``ws://127.0.0.1:8765`` (the host and port
given here), and add a 3D panel for ``/fields/*`` and ``/swarm/positions`` and a Plot
panel for ``/metrics``.

The server is a sink beside the MCAP writer, never in its path: it receives the bytes
that were written, copies them into foxglove-sdk's per-client queues (bounded; the
oldest message is dropped for a slow client) and returns. A channel nobody subscribes
to is skipped before any copy, so a run without clients pays one dictionary lookup and
one flag test per message. The server uses its own :class:`foxglove.Context`, so it
never sees channels of other code in the process and other sinks never see its own.
Message times are the simulated times of the log (integer ns from t = 0), so Foxglove
shows the run's clock starting at the epoch.
"""

from __future__ import annotations

import errno
import socket
import sys
import threading

import foxglove

from harness.components import ParameterError, flag, integer, require
from harness.observers import RunContext, Status
from harness.records import StepRecord

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765


class LiveServerError(RuntimeError):
    """The live server could not start (for example, its port is in use)."""


class LiveServer:
    """A Foxglove WebSocket server for the topics of a run.

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
        try:
            self._server = foxglove.start_server(
                name=name,
                host=host,
                port=port,
                context=self._context,
                message_backlog_size=backlog,
            )
        except RuntimeError as err:
            cause = str(err).removeprefix("FoxgloveError: ").strip()
            raise LiveServerError(
                f"live view: cannot serve on ws://{host}:{port}: {cause} "
                f"(choose another log.live_port or stop the program using it)"
            ) from None
        self.port: int = self._server.port
        self._closed = False

    @property
    def url(self) -> str:
        """``ws://host:port``, the address to open in Foxglove."""
        return f"ws://{self.host}:{self.port}"

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
        """Send one message to the clients subscribed to ``topic``; never blocks.

        Args:
            topic: An advertised topic (see :meth:`channel`); others are ignored.
            log_time_ns: Message time (integer ns of simulated time).
            data: The serialized message, byte for byte as written to the log.
        """
        ch = self._channels.get(topic)
        if ch is None or self._closed or not ch.has_sinks():
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
    refused ``port`` (:class:`~harness.components.ParameterError`), raised before the log
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
                        f"a port free to serve on (ws://{self.host}:{self.port}: "
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
