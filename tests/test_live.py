"""Live view: a WebSocket client receives the run's messages; the log is unchanged.

The client speaks Foxglove's WebSocket protocol with the ``websockets`` package. The
foxglove-sdk server (0.30) accepts the subprotocol ``foxglove.sdk.v1`` (the renamed
``foxglove.websocket.v1``: same JSON control messages and binary message frames
``0x01 | u32 subscription id | u64 log time | payload``, time frames
``0x02 | u64 time``); clients offering the old name reach it through the server's
shim. Grids are decoded with a protobuf class built from the schema the server
advertises and a strided read of the ``foxglove.Grid`` layout written here, not with the
project's loader.
"""

import asyncio
import base64
import json
import socket
import struct
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader
from mcap_protobuf.schema import build_file_descriptor_set

import harness.observers.live
import harness.observers.log
import harness.runs.run as harness_run
from analysis.load import load_run
from harness.grid import Grid
from harness.observers.live import LiveServer, LiveServerError
from harness.observers.log import METRICS_SCHEMA, GridMsg, McapLogger, grid_message, time_ns

websockets = pytest.importorskip("websockets")

SUBPROTOCOL = "foxglove.sdk.v1"
LEGACY = "foxglove.websocket.v1"
WAIT_S = 10.0  # bound on every wait


class Client:
    """A Foxglove WebSocket client on its own thread: subscribes to ``topics`` as soon
    as they are advertised and keeps every message as ``(topic, log_time, payload,
    monotonic receive time)``.
    """

    def __init__(
        self, url: str, topics: set[str], read: bool = True, offer: tuple[str, ...] = (SUBPROTOCOL,)
    ) -> None:
        self.url, self.topics, self.read, self.offer = url, topics, read, offer
        self.channels: dict[str, dict] = {}
        self.messages: list[tuple[str, int, bytes, float]] = []
        self.times: list[tuple[int, int]] = []  # (server time, messages received before it)
        self.server_info: dict = {}
        self.subprotocol: str | None = None
        self.connected = threading.Event()
        self.subscribed: set[str] = set()
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=lambda: asyncio.run(self._main()), daemon=True)

    def __enter__(self) -> "Client":
        self._thread.start()
        assert self.connected.wait(WAIT_S), f"no connection to {self.url}"
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(WAIT_S)
        assert not self._thread.is_alive()

    def check(self) -> None:
        if self._error is not None:
            raise self._error

    async def _main(self) -> None:
        try:
            async with websockets.connect(
                self.url,
                subprotocols=list(self.offer),
                proxy=None,
                open_timeout=WAIT_S,
                close_timeout=2,
            ) as ws:
                self.subprotocol = ws.subprotocol
                assert ws.subprotocol in self.offer
                self.connected.set()
                by_sub: dict[int, str] = {}
                while not self._stop.is_set():
                    if not self.read and self.subscribed >= self.topics:
                        await asyncio.sleep(0.05)  # a stalled client: reads nothing more
                        continue
                    try:
                        frame = await asyncio.wait_for(ws.recv(), 0.1)
                    except TimeoutError:
                        continue
                    if isinstance(frame, str):
                        msg = json.loads(frame)
                        unknown = msg.get("op") == "status" and "Unknown channel ID" in msg.get(
                            "message", ""
                        )
                        if unknown:
                            # foxglove-sdk 0.30 can reject a subscription that arrives right
                            # after the advertisement of a new channel: ask again
                            channel_id = int(msg["message"].rsplit(":", 1)[1])
                            sub_id = next(
                                k for k, v in by_sub.items() if self.channels[v]["id"] == channel_id
                            )
                            await asyncio.sleep(0.05)
                            sub = {"id": sub_id, "channelId": channel_id}
                            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [sub]}))
                        if msg.get("op") == "serverInfo":
                            self.server_info = msg
                        if msg.get("op") == "advertise":
                            subs = []
                            for ch in msg["channels"]:
                                self.channels[ch["topic"]] = ch
                                if ch["topic"] in self.topics:
                                    sub_id = len(by_sub) + 1
                                    by_sub[sub_id] = ch["topic"]
                                    subs.append({"id": sub_id, "channelId": ch["id"]})
                                    self.subscribed.add(ch["topic"])
                            if subs:
                                await ws.send(
                                    json.dumps({"op": "subscribe", "subscriptions": subs})
                                )
                    elif frame[0] == 0x01:
                        sub_id, log_time = struct.unpack_from("<IQ", frame, 1)
                        self.messages.append(
                            (by_sub[sub_id], log_time, bytes(frame[13:]), time.monotonic())
                        )
                    elif frame[0] == 0x02:
                        self.times.append(
                            (struct.unpack_from("<Q", frame, 1)[0], len(self.messages))
                        )
        except BaseException as err:  # reported to the test thread by check()
            self._error = err
            self.connected.set()

    def wait_for(self, predicate, what: str) -> None:
        deadline = time.monotonic() + WAIT_S
        while not predicate():
            self.check()
            assert time.monotonic() < deadline, f"timed out waiting for {what}"
            time.sleep(0.01)


def grid_class_from_schema(channel: dict):
    """The protobuf class of an advertised channel (schema: base64 FileDescriptorSet)."""
    assert channel["schemaEncoding"] == "protobuf" and channel["encoding"] == "protobuf"
    fds = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for file in fds.file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


def decode_grid(msg) -> dict[str, np.ndarray]:
    """Each float32 field of a ``foxglove.Grid`` as an ``(rows, columns)`` array, read
    with the message's own strides and offsets.
    """
    buf = bytes(msg.data)
    cols = msg.column_count
    rows = len(buf) // msg.row_stride
    out = {}
    for f in msg.fields:
        assert f.type == 7  # FLOAT32 in foxglove.PackedElementField
        out[f.name] = np.ndarray(
            (rows, cols),
            dtype="<f4",
            buffer=buf,
            offset=f.offset,
            strides=(msg.row_stride, msg.cell_stride),
        ).copy()
    return out


def grid_schema() -> tuple[str, str, bytes, str]:
    data = build_file_descriptor_set(GridMsg).SerializeToString()
    return ("foxglove.Grid", "protobuf", data, "protobuf")


def metrics_schema() -> tuple[str, str, bytes, str]:
    return ("densityloop.Metrics", "jsonschema", json.dumps(METRICS_SCHEMA).encode(), "json")


def test_client_receives_and_decodes_a_grid():
    rng = np.random.default_rng(11)
    grid = Grid.square(7)
    values = rng.random((1, grid.ny, grid.nx)) * 3.0
    with LiveServer(port=0) as server:
        assert server.port > 0 and server.url == f"ws://127.0.0.1:{server.port}"
        server.channel("/fields/p_hat", *grid_schema())
        server.channel("/metrics", *metrics_schema())
        with Client(server.url, {"/fields/p_hat", "/metrics"}) as client:
            client.wait_for(
                lambda: server.subscribed("/fields/p_hat") and server.subscribed("/metrics"),
                "the subscriptions",
            )
            msg = grid_message(grid, 0.25, ("p",), values)
            server.publish("/fields/p_hat", time_ns(0.25), msg.SerializeToString())
            server.publish("/metrics", time_ns(0.25), b'{"t": 0.25, "phi_l2": 1.5}')
            client.wait_for(lambda: len(client.messages) >= 2, "two messages")
            client.check()
        cls = grid_class_from_schema(client.channels["/fields/p_hat"])
    assert client.channels["/metrics"]["schemaName"] == "densityloop.Metrics"
    assert json.loads(client.channels["/metrics"]["schema"]) == METRICS_SCHEMA
    got = {topic: (t, payload) for topic, t, payload, _ in client.messages}
    t, payload = got["/fields/p_hat"]
    assert t == 250_000_000
    decoded = cls.FromString(payload)
    assert (decoded.column_count, decoded.cell_size.x) == (grid.nx, grid.dx)
    np.testing.assert_array_equal(decode_grid(decoded)["p"], values[0].astype(np.float32))
    assert json.loads(got["/metrics"][1]) == {"t": 0.25, "phi_l2": 1.5}


def ipv6_loopback() -> bool:
    """Whether this machine can bind the IPv6 loopback ``::1``."""
    try:
        with socket.socket(socket.AF_INET6, socket.SOCK_STREAM) as s:
            s.bind(("::1", 0))
    except OSError:
        return False
    return True


@pytest.mark.parametrize(
    "host, url",
    [
        ("127.0.0.1", "ws://127.0.0.1:8765"),
        ("localhost", "ws://localhost:8765"),
        ("::1", "ws://[::1]:8765"),
        ("[::1]", "ws://[::1]:8765"),
        ("fe80::1%eth0", "ws://[fe80::1%25eth0]:8765"),
    ],
)
def test_the_live_view_s_address_is_a_url_for_every_host(host, url):
    from urllib.parse import urlsplit

    from harness.observers.live import ws_url

    assert ws_url(host, 8765) == url
    assert urlsplit(url).port == 8765


@pytest.mark.skipif(not ipv6_loopback(), reason="no IPv6 loopback here")
def test_a_live_view_on_an_ipv6_host_prints_a_url_a_client_connects_to():
    with LiveServer(host="::1", port=0) as server:
        assert server.url == f"ws://[::1]:{server.port}"
        server.channel("/metrics", *metrics_schema())
        with Client(server.url, {"/metrics"}) as client:
            client.wait_for(lambda: server.subscribed("/metrics"), "subscribed over IPv6")


@pytest.mark.parametrize("offer", [(LEGACY,), (SUBPROTOCOL,), (LEGACY, SUBPROTOCOL)])
def test_either_subprotocol_name_connects_and_gets_the_simulated_clock(offer):
    # Foxglove Studio 1.x offers only the old name; the server answers with the name the
    # client offered, advertises the time capability and sends the simulated time before
    # the messages of that time
    with LiveServer(port=0) as server:
        server.channel("/metrics", *metrics_schema())
        with Client(server.url, {"/metrics"}, offer=offer) as client:
            client.wait_for(lambda: server.subscribed("/metrics"), "the subscription")
            for t in (0.0, 0.02, 0.04):
                server.publish("/metrics", time_ns(t), json.dumps({"t": t}).encode())
            client.wait_for(lambda: len(client.messages) == 3, "three messages")
            client.check()
    assert client.subprotocol == (SUBPROTOCOL if SUBPROTOCOL in offer else LEGACY)
    assert "time" in client.server_info["capabilities"]
    assert [m[1] for m in client.messages] == [0, 20_000_000, 40_000_000]
    # the clock: each new time once, in order. foxglove-sdk sends it on its control
    # queue and the messages on their data queue, drained in no fixed order: a burst of
    # messages can arrive before or after the times sent between them
    assert [t for t, _ in client.times] == [0, 20_000_000, 40_000_000]


def test_a_client_offering_another_protocol_is_refused():
    with LiveServer(port=0) as server:
        with pytest.raises(websockets.exceptions.InvalidStatus):
            with Client(server.url, set(), offer=("other.v1",)) as client:
                client.check()


def test_unsubscribed_topics_and_closed_server_are_silent():
    with LiveServer(port=0) as server:
        server.channel("/fields/p_hat", *grid_schema())
        server.channel("/fields/p_hat", *metrics_schema())  # a known topic is kept as is
        server.channel("/metrics", *metrics_schema())
        with Client(server.url, {"/metrics"}) as client:
            client.wait_for(lambda: server.subscribed("/metrics"), "the subscription")
            assert not server.subscribed("/fields/p_hat")
            server.publish("/fields/p_hat", 1, b"not sent")
            server.publish("/unknown", 2, b"ignored")
            server.publish("/metrics", 3, b'{"t": 0.0}')
            client.wait_for(lambda: client.messages, "a message")
            time.sleep(0.2)
        assert [(m[0], m[1]) for m in client.messages] == [("/metrics", 3)]
        assert client.channels["/fields/p_hat"]["schemaName"] == "foxglove.Grid"
    server.publish("/metrics", 4, b"{}")  # after close: a no-op
    server.close()


def test_a_stalled_client_does_not_block_publishing():
    # a client that stops reading: the server's per-client queue drops old messages,
    # publish() returns; 200 MB is far beyond the socket buffers
    payload = bytes(100_000)
    done = threading.Event()
    with LiveServer(port=0, backlog=16) as server:
        server.channel("/metrics", *metrics_schema())
        with Client(server.url, {"/metrics"}, read=False) as client:
            client.wait_for(lambda: server.subscribed("/metrics"), "the subscription")

            def flood() -> None:
                for i in range(2000):
                    server.publish("/metrics", i, payload)
                done.set()

            threading.Thread(target=flood, daemon=True).start()
            assert done.wait(60.0), "publish() blocked behind a client that does not read"


def test_port_in_use_is_one_clear_line():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(LiveServerError) as info:
            LiveServer(port=port)
    text = str(info.value)
    assert "\n" not in text and f"ws://127.0.0.1:{port}" in text and "in use" in text


# --- a tiny run with the live view on --------------------------------------------------

TINY = [
    "grid.n=10",
    "agents.n=150",
    "sim.t_final=0.2",
    "sim.dt=0.02",
    "log.field_every=2",
    "log.positions_every=3",
    "log.progress=off",
    "seed=5",
]


def mcap_contents(path: Path):
    """Schemas, channels, messages and metadata of a log (provenance without its
    wall-clock values)."""
    with open(path, "rb") as f:
        reader = make_reader(f)
        messages = [
            (ch.topic, m.log_time, m.publish_time, m.data)
            for _, ch, m in reader.iter_messages(log_time_order=False)
        ]
        summary = reader.get_summary()
        schemas = sorted((s.id, s.name, s.encoding, s.data) for s in summary.schemas.values())
        channels = sorted(
            (c.id, c.topic, c.message_encoding, c.schema_id) for c in summary.channels.values()
        )
        metadata = {
            m.name: {k: v for k, v in m.metadata.items() if k != "start_time_utc"}
            for m in reader.iter_metadata()
        }
    return schemas, channels, messages, metadata


def test_live_run_publishes_while_running_and_leaves_the_log_unchanged(
    tmp_path, monkeypatch, compose
):
    off = harness_run.run(compose(TINY), tmp_path / "off")
    assert off.state == "completed"

    watched = ("/metrics", "/fields/p_hat")
    received_before_end: list[int] = []
    with LiveServer(port=0) as server:

        class KeptOpen:
            """The test's server as ``log.live`` builds it; the run's close is deferred
            to the test so the client can drain what was sent."""

            def __init__(self, host, port):
                assert (host, port) == ("127.0.0.1", 8765)

            def __getattr__(self, name):
                return getattr(server, name)

            def close(self):
                pass

        class WaitingLogger(McapLogger):
            """The run's logger; after the first message on each watched topic it waits
            (bounded) for the client's subscription, so the rest of the run is seen live.
            """

            def open(self, *args, **kwargs):
                super().open(*args, **kwargs)
                assert self.live is not None  # log.live=true reached the logger
                self._waited: set[str] = set()

            def _write(self, topic, t, data, schema_id, encoding):
                super()._write(topic, t, data, schema_id, encoding)
                if topic in watched and topic not in self._waited:
                    self._waited.add(topic)
                    deadline = time.monotonic() + WAIT_S
                    while not server.subscribed(topic):
                        assert time.monotonic() < deadline, f"no subscription to {topic}"
                        time.sleep(0.01)

            def finalize(self, *args, **kwargs):
                # the run is still open here: wait (bounded) for delivery, which a loaded
                # machine can delay, then count what arrived before the log is finalised
                deadline = time.monotonic() + WAIT_S
                while not client.messages and time.monotonic() < deadline:
                    time.sleep(0.01)
                received_before_end.append(len(client.messages))
                super().finalize(*args, **kwargs)

        monkeypatch.setattr(harness.observers.live, "LiveServer", KeptOpen)
        monkeypatch.setattr(harness.observers.log, "McapLogger", WaitingLogger)
        with Client(server.url, set(watched)) as client:
            on = harness_run.run(compose([*TINY, "log.live=true"]), tmp_path / "on")
            assert on.state == "completed"
            n_metrics = round(0.2 / 0.02) + 1
            # every /metrics message after the subscription (the first went out before)
            client.wait_for(
                lambda: sum(m[0] == "/metrics" for m in client.messages) >= n_metrics - 1,
                "the run's metrics",
            )
            client.check()
        cls = grid_class_from_schema(client.channels["/fields/p_hat"])

    # messages arrived while the run was going, not only after it ended
    assert received_before_end and received_before_end[0] > 0
    # the live view changed no byte of the log: schemas, channels, every message and
    # the metadata (the config records differ only in log.live; wall times differ)
    on_log = mcap_contents(tmp_path / "on" / "run.mcap")
    off_log = mcap_contents(tmp_path / "off" / "run.mcap")
    assert on_log[:3] == off_log[:3]
    for log in (on_log, off_log):
        config = yaml.safe_load(log[3]["config"]["yaml"])
        config["log"]["live"] = config["observers"]["live"]["enabled"] = False
        log[3]["config"]["yaml"] = config
        log[3]["status"].pop("wall_s")
    assert on_log[3] == off_log[3]
    # what the client received is what the log holds, message for message
    _, _, logged, _ = mcap_contents(tmp_path / "on" / "run.mcap")
    logged_by_key = {(topic, t): data for topic, t, _, data in logged}
    for topic, t, payload, _ in client.messages:
        assert logged_by_key[(topic, t)] == payload
    # one Grid decoded back to the array that was logged (numpy loader, float32 values)
    grids = [(t, p) for topic, t, p, _ in client.messages if topic == "/fields/p_hat"]
    assert grids
    t_ns, payload = grids[-1]
    live = decode_grid(cls.FromString(payload))["p"]
    series = load_run(tmp_path / "on").fields["/fields/p_hat"]
    i = int(np.argmin(np.abs(series.t - t_ns / 1e9)))
    assert abs(series.t[i] * 1e9 - t_ns) < 1
    np.testing.assert_array_equal(live.astype(float), series.values[i, 0])
    # the last grid is the run's final estimate: it integrates to about 1 (density)
    assert abs(live.sum() * 0.1 * 0.1 - 1.0) < 0.5


def test_live_port_in_use_is_one_line_and_exit_2(tmp_path):
    import socket
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        proc = subprocess.run(
            [
                sys.executable,
                "-m",
                "experiments.closed_loop",
                *TINY,
                "log.live=true",
                f"log.live_port={port}",
                f"hydra.run.dir={tmp_path}",
            ],
            capture_output=True,
            text=True,
            cwd=root,
            timeout=120,
        )
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().startswith(f"invalid config: log.live_port={port}")
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "run.mcap").exists()
