"""A real viewer opens a run: Foxglove Studio 1.48 in headless Chromium.

The viewer is the prebuilt web bundle of ``@foxglove/studio-base`` 1.48.0 (the last
open-source Foxglove Studio), pinned with its integrity hash in
``viewer/package-lock.json`` and installed with React 17 into ``viewer/node_modules`` by
``scripts/viewer_deps.sh``; ``viewer/index.html`` renders its ``App`` as the Studio web
app does. A threaded HTTP server on 127.0.0.1 (with the byte ranges Studio's remote-file
reader needs) serves the page, the bundle, the log and ``layouts/densityloop.json``.
Chromium is Debian's, driven over the Chrome DevTools Protocol with ``websockets``
(already a dev dependency): no browser download, no driver package.

What is checked comes from the viewer's own page, not from this project's code: the
topic list, the value the Plot legend shows (compared with the log read by the ``mcap``
package), coloured pixels of a plotted line, the ``Player problem`` lines Studio logs to
the console, and for the live view the start time Studio shows. Each test keeps its
screenshot (``viewer.png`` in the test's ``tmp_path``; with ``DENSITYLOOP_VIEWER_SHOTS``
set, also copied to that folder) and prints its path.
"""

from __future__ import annotations

import base64
import contextlib
import functools
import http.server
import io
import json
import math
import os
import re
import shutil
import subprocess
import threading
import time
import urllib.request
from contextlib import ExitStack
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
from mcap.reader import make_reader

from harness.grid import Grid
from harness.observers.live import LiveServer
from harness.observers.log import ALWAYS_NUMBERS, FIELD_TOPICS, METRIC_KEYS, METRICS_SCHEMA
from harness.runs.run import run as run_config
from harness.targets.densities import DEFAULT_TARGET

websockets_sync = pytest.importorskip("websockets.sync.client")

ROOT = Path(__file__).resolve().parents[1]
VIEWER = ROOT / "viewer"
LAYOUT = ROOT / "layouts" / "densityloop.json"
STUDIO = VIEWER / "node_modules" / "@foxglove" / "studio-base"
STUDIO_VERSION = "1.48.0"
CHROMIUM = shutil.which("chromium")
VIEWPORT = (1600, 1000)  # CSS pixels
LOAD_S = 60.0  # bound on loading the page and the data (the machine may be busy)


def _missing() -> str | None:
    if CHROMIUM is None:
        return "no chromium on PATH (scripts/viewer_deps.sh installs Debian's package as root)"
    try:
        version = json.loads((STUDIO / "package.json").read_text())["version"]
    except (OSError, ValueError, KeyError):
        return "viewer/node_modules missing (scripts/viewer_deps.sh runs npm ci in viewer/)"
    if version != STUDIO_VERSION:
        return f"viewer/node_modules has studio-base {version}, not {STUDIO_VERSION}: rerun npm ci"
    return None


needs_viewer = pytest.mark.skipif(_missing() is not None, reason=f"real viewer: {_missing()}")


# --- serving the page ------------------------------------------------------------------


class _Handler(http.server.SimpleHTTPRequestHandler):
    """Static files from ``viewer/`` plus named extra files, with single byte ranges."""

    extra: ClassVar[dict[str, Path]] = {}

    def log_message(self, format: str, *args: object) -> None:
        pass

    def translate_path(self, path: str) -> str:
        name = path.split("?", 1)[0]
        if name in self.extra:
            return str(self.extra[name])
        return super().translate_path(path)

    def end_headers(self) -> None:
        self.send_header("Accept-Ranges", "bytes")
        self.send_header("Cache-Control", "no-store")
        super().end_headers()

    def send_head(self):  # type: ignore[no-untyped-def]
        path = Path(self.translate_path(self.path))
        wanted = re.fullmatch(r"bytes=(\d+)-(\d*)", self.headers.get("Range", ""))
        self._length = None
        if wanted is None or not path.is_file():
            return super().send_head()
        size = path.stat().st_size
        first = int(wanted[1])
        last = min(int(wanted[2]) if wanted[2] else size - 1, size - 1)
        if first > last:
            self.send_error(416)
            return None
        f = open(path, "rb")  # the base class closes it after copyfile
        f.seek(first)
        self.send_response(206)
        self.send_header("Content-Type", self.guess_type(str(path)))
        self.send_header("Content-Range", f"bytes {first}-{last}/{size}")
        self.send_header("Content-Length", str(last - first + 1))
        self.end_headers()
        self._length = last - first + 1
        return f

    def copyfile(self, source, outputfile) -> None:  # type: ignore[no-untyped-def]
        try:
            if self._length is None:
                super().copyfile(source, outputfile)
            else:
                outputfile.write(source.read(self._length))
        except (BrokenPipeError, ConnectionResetError):
            pass  # Studio aborts its first GET once it has the headers


@pytest.fixture
def serve():
    """``serve(extra)``: the base URL of a server for ``viewer/`` and ``extra`` files
    (URL path -> file)."""
    servers: list[http.server.ThreadingHTTPServer] = []

    def start(extra: dict[str, Path]) -> str:
        handler = type("Handler", (_Handler,), {"extra": dict(extra)})
        httpd = http.server.ThreadingHTTPServer(
            ("127.0.0.1", 0), functools.partial(handler, directory=str(VIEWER))
        )
        httpd.daemon_threads = True
        threading.Thread(target=httpd.serve_forever, daemon=True).start()
        servers.append(httpd)
        return f"http://127.0.0.1:{httpd.server_address[1]}"

    yield start
    for httpd in servers:
        httpd.shutdown()
        httpd.server_close()


# --- driving Chromium ------------------------------------------------------------------


class Page:
    """One Chromium tab over the DevTools protocol: commands, console and screenshots."""

    def __init__(self, ws_url: str) -> None:
        self._stack = ExitStack()
        self._ws = self._stack.enter_context(
            websockets_sync.connect(ws_url, max_size=None, proxy=None)
        )
        self._id = 0
        self.console: list[tuple[str, str, list[dict]]] = []  # (type, text, raw args)
        self.exceptions: list[str] = []
        for domain in ("Runtime", "Page", "Log"):
            self.call(f"{domain}.enable")
        width, height = VIEWPORT
        self.call(
            "Emulation.setDeviceMetricsOverride",
            width=width,
            height=height,
            deviceScaleFactor=1,
            mobile=False,
        )

    def _event(self, msg: dict) -> None:
        method, params = msg.get("method"), msg.get("params", {})
        if method == "Runtime.consoleAPICalled":
            text = " ".join(
                str(a.get("value", a.get("description", a.get("type")))) for a in params["args"]
            )
            self.console.append((params["type"], text, params["args"]))
        elif method == "Runtime.exceptionThrown":
            details = params["exceptionDetails"]
            self.exceptions.append(details.get("exception", {}).get("description", str(details)))
        elif method == "Log.entryAdded":
            entry = params["entry"]
            self.console.append((f"log-{entry['level']}", entry["text"], []))

    def call(self, method: str, **params: object) -> dict:
        """Send a command and wait (bounded) for its result; events seen meanwhile are kept."""
        self._id += 1
        self._ws.send(json.dumps({"id": self._id, "method": method, "params": params}))
        deadline = time.monotonic() + LOAD_S
        while True:
            msg = json.loads(self._ws.recv(timeout=max(0.1, deadline - time.monotonic())))
            if msg.get("id") == self._id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})
            self._event(msg)

    def evaluate(self, expression: str) -> object:
        """The value of a JavaScript expression in the page."""
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        return result.get("result", {}).get("value")

    def text(self) -> str:
        return str(self.evaluate("document.body ? document.body.innerText : ''"))

    def wait_for(self, predicate, what: str, timeout: float = LOAD_S) -> None:  # type: ignore[no-untyped-def]
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                raise AssertionError(f"viewer: timed out waiting for {what}")
            time.sleep(0.25)

    def describe(self, arg: dict) -> str:
        """A console argument (an object) as JSON, for messages."""
        if "objectId" not in arg:
            return str(arg.get("value", arg.get("description")))
        result = self.call(
            "Runtime.callFunctionOn",
            objectId=arg["objectId"],
            functionDeclaration=(
                "function() { return JSON.stringify(this, (k, v) => "
                "v instanceof Error ? String(v) : v); }"
            ),
            returnByValue=True,
        )
        return str(result.get("result", {}).get("value"))

    def problems(self) -> list[str]:
        """Studio's ``Player problem`` console lines, with the problem object."""
        return [
            " ".join(self.describe(a) for a in args) or text
            for kind, text, args in self.console
            if text.startswith("Player problem")
        ]

    def screenshot(self, clip: dict | None = None) -> bytes:
        params: dict[str, object] = {"format": "png"}
        if clip is not None:
            params["clip"] = {**clip, "scale": 1}
        return base64.b64decode(self.call("Page.captureScreenshot", **params)["data"])

    def close(self) -> None:
        self._stack.close()


@pytest.fixture
def browser(tmp_path):
    """``open(url)``: a :class:`Page` of a fresh headless Chromium at ``url``."""
    procs: list[subprocess.Popen] = []
    pages: list[Page] = []

    def open_page(url: str) -> Page:
        profile = tmp_path / f"chromium-profile-{len(procs)}"
        cmd = [
            str(CHROMIUM),
            "--headless",
            "--no-sandbox",  # root in CI
            "--disable-gpu",
            # WebGL for the 3D panels in software (Chromium no longer falls back by itself)
            "--use-angle=swiftshader",
            "--enable-unsafe-swiftshader",
            # nothing but loopback: no update, sync or QUIC probes to closed networks
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            f"--user-data-dir={profile}",
            "--remote-debugging-port=0",
            f"--window-size={VIEWPORT[0]},{VIEWPORT[1]}",
            "about:blank",
        ]
        proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True)
        procs.append(proc)
        port_file = profile / "DevToolsActivePort"
        deadline = time.monotonic() + LOAD_S
        while not port_file.exists() or len(port_file.read_text().splitlines()) < 2:
            assert proc.poll() is None, f"chromium exited: {proc.stderr.read()[-2000:]}"
            assert time.monotonic() < deadline, "chromium did not open its DevTools port"
            time.sleep(0.05)
        threading.Thread(target=proc.stderr.read, daemon=True).start()  # keep the pipe drained
        port = int(port_file.read_text().splitlines()[0])
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10) as r:
            target = next(t for t in json.load(r) if t["type"] == "page")
        page = Page(target["webSocketDebuggerUrl"])
        pages.append(page)
        page.call("Page.navigate", url=url)
        return page

    yield open_page
    for page in pages:
        page.close()
    for proc in procs:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def keep(png: bytes, tmp_path: Path, name: str) -> Path:
    """Write a screenshot under the test's output (and to ``DENSITYLOOP_VIEWER_SHOTS``)."""
    path = tmp_path / name
    path.write_bytes(png)
    if shots := os.environ.get("DENSITYLOOP_VIEWER_SHOTS"):
        Path(shots).mkdir(parents=True, exist_ok=True)
        shutil.copy(path, Path(shots) / name)
    print(f"viewer screenshot: {path}")
    return path


def topic_listed(text: str, topic: str, schema: str) -> bool:
    """Whether the Topics list shows ``topic`` with its schema name (its two lines)."""
    return f"\n{topic}\n{schema}\n" in text


def coloured_pixels(png: bytes) -> int:
    """Pixels of a screenshot whose colour is far from grey (plotted lines, not axes)."""
    from matplotlib.image import imread

    rgb = imread(io.BytesIO(png), format="png")[..., :3]
    return int(np.sum(rgb.max(axis=-1) - rgb.min(axis=-1) > 0.3))


def element_rect(page: Page, selector_js: str) -> dict | None:
    """``{x, y, width, height}`` of the element an expression returns, or None."""
    rect = page.evaluate(
        f"(() => {{ const e = {selector_js}; if (!e) return null; const r = "
        "e.getBoundingClientRect(); return {x: r.x, y: r.y, width: r.width, height: r.height}; })()"
    )
    return rect if isinstance(rect, dict) else None


PLOT_CANVAS = """(() => {
  const title = [...document.querySelectorAll('*')].find(
    (e) => e.childElementCount === 0 && e.textContent.startsWith('Fig. 2'));
  let panel = title;
  while (panel && !panel.querySelector('canvas')) panel = panel.parentElement;
  return panel ? panel.querySelector('canvas') : null;
})()"""


LEGEND = re.compile(r"/metrics\.phat_target_l2\s*\n\s*(-?[0-9.]+(?:e-?\d+)?)")
"""The Plot legend's line for ``phat_target_l2`` and the value it shows."""


def metrics_of(path: Path) -> list[dict]:
    """The ``/metrics`` messages of a log, read with the ``mcap`` package."""
    with open(path, "rb") as f:
        return [json.loads(m.data) for _, _, m in make_reader(f).iter_messages(topics=["/metrics"])]


# --- the tests -------------------------------------------------------------------------


def test_layout_names_logged_topics_and_spans_the_target():
    layout = json.loads(LAYOUT.read_text())
    panels = layout["configById"]

    def leaves(node: object) -> list[str]:
        if isinstance(node, str):
            return [node]
        assert isinstance(node, dict) and node["direction"] in ("row", "column")
        return leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(panels)
    kinds = sorted(name.split("!")[0] for name in panels)
    assert kinds == ["3D", "3D", "Plot", "RawMessages"]
    grids = {}
    for name, config in panels.items():
        if name.startswith("3D!"):
            topics = config["topics"]
            assert set(topics) <= {*FIELD_TOPICS, "/swarm/positions", "/domain/obstacles"}
            assert topics["/swarm/positions"]["visible"]
            assert topics["/domain/obstacles"]["visible"]  # with the robots and the field
            (field,) = (t for t in topics if t.startswith("/fields/"))
            grids[field] = topics[field]
        elif name.startswith("Plot!"):
            keys = [path["value"].removeprefix("/metrics.") for path in config["paths"]]
            assert keys == ["phat_target_l2", "swarm_l2", "phi_l2"]  # Fig. 2
            assert set(keys) <= set(METRIC_KEYS)
        else:
            assert config["topicPath"] == "/metrics"
    assert set(grids) == {"/fields/p_hat", "/fields/p_target"}
    # one colour scale for the estimate and the target, spanning the default target's
    # values on the default grid without washing them out
    p = DEFAULT_TARGET.on_grid(Grid.square(30))
    for settings in grids.values():
        assert settings["colorField"] == "p" and settings["colorMode"] == "colormap"
        assert settings["minValue"] <= p.min() < p.max() <= settings["maxValue"]
        assert settings["maxValue"] <= 1.1 * p.max()


RUN = (
    "grid.n=16",
    "agents.n=200",
    "sim.t_final=0.5",
    "sim.dt=0.02",
    "log.field_every=5",
    "log.positions_every=5",
    "log.progress=off",
)
"""A short run: 26 steps on a 16 x 16 grid with 200 robots."""


@needs_viewer
def test_studio_opens_a_run_with_the_layout(tmp_path, compose, serve, browser):
    t0 = time.monotonic()
    run_dir = tmp_path / "run"
    assert run_config(compose(RUN), run_dir).state == "completed"
    log = run_dir / "run.mcap"
    base = serve({"/run.mcap": log, "/layout.json": LAYOUT})
    page = browser(
        f"{base}/index.html?ds=remote-file&ds.url={base}/run.mcap"
        f"&dl.layout={base}/layout.json&layoutId=densityloop"
    )
    try:
        # the layout's panels, the topics with their schemas, a value in the Plot legend
        page.wait_for(lambda: "Fig. 2" in page.text(), "the layout's Plot panel")
        page.wait_for(
            lambda: topic_listed(page.text(), "/metrics", "densityloop.Metrics"),
            "/metrics in the topic list",
        )
        text = page.text()
        assert topic_listed(text, "/fields/p_hat", "foxglove.Grid")
        assert topic_listed(text, "/swarm/positions", "foxglove.PointCloud")
        assert "estimate p_hat" in text and "target p_*" in text  # the 3D panels' titles
        page.wait_for(lambda: LEGEND.search(page.text()) is not None, "a plotted value")
        # Studio starts at the first time + 99 ms: the legend shows the last value there
        # once it has settled (on a loaded machine it first shows a value on its way there)
        logged = [m["phat_target_l2"] for m in metrics_of(log) if m["t"] <= 0.099 + 1e-9]

        def shown() -> float:
            found = LEGEND.search(page.text())
            return math.nan if found is None else float(found[1])

        with contextlib.suppress(AssertionError):
            page.wait_for(lambda: shown() == pytest.approx(logged[-1], rel=1e-12), "the value")
        assert shown() == pytest.approx(logged[-1], rel=1e-12)
        # the lines themselves: coloured pixels in the right half of the plot, where the
        # floating legend never is (axes and grid lines are grey)
        rect = element_rect(page, PLOT_CANVAS)
        assert rect is not None and rect["width"] > 100, "no plot canvas"
        half = {**rect, "x": rect["x"] + rect["width"] / 2, "width": rect["width"] / 2}
        page.wait_for(lambda: coloured_pixels(page.screenshot(half)) > 100, "the plotted lines")
        # Raw Messages shows a missing value as null
        null = re.compile(r"\nswarm_w2\s*\nnull\n")  # the key, a no-break space, the value
        page.wait_for(lambda: null.search(page.text()) is not None, "a null in Raw Messages")
        time.sleep(1.0)  # let the 3D panels draw their first frames
    finally:
        path = keep(page.screenshot(), tmp_path, "viewer.png")
    assert page.problems() == [], f"Studio reported problems (screenshot {path})"
    assert page.exceptions == [], f"uncaught exceptions in the page (screenshot {path})"
    print(f"viewer test wall time: {time.monotonic() - t0:.1f} s")


def grey_pixels(png: bytes) -> int:
    """Pixels of a screenshot of the obstacles' grey (RGB near 0.5, 0.5, 0.5)."""
    from matplotlib.image import imread

    rgb = imread(io.BytesIO(png), format="png")[..., :3]
    return int((np.abs(rgb - 0.5).max(axis=-1) < 0.06).sum())


@needs_viewer
def test_studio_opens_a_run_on_the_rooms_with_its_obstacles(tmp_path, compose, serve, browser):
    """A run on a domain with obstacles: Studio lists the domain's topics with their
    schemas, reports no problem decoding them, and the 3D panels draw grey obstacles."""
    run_dir = tmp_path / "run"
    overrides = (*RUN, "domain=rooms", "init=left_room")
    assert run_config(compose(overrides), run_dir).state == "completed"
    base = serve({"/run.mcap": run_dir / "run.mcap", "/layout.json": LAYOUT})
    page = browser(
        f"{base}/index.html?ds=remote-file&ds.url={base}/run.mcap"
        f"&dl.layout={base}/layout.json&layoutId=densityloop"
    )
    try:
        page.wait_for(
            lambda: topic_listed(page.text(), "/domain/obstacles", "foxglove.SceneUpdate"),
            "/domain/obstacles in the topic list",
        )
        assert topic_listed(page.text(), "/domain/mask", "foxglove.Grid")
        # the rooms' wall in both 3D panels: about 14 000 grey pixels, against about 3 400
        # of the page's own greys in the screenshot of a run on the square
        page.wait_for(lambda: grey_pixels(page.screenshot()) > 8000, "the grey obstacles")
    finally:
        path = keep(page.screenshot(), tmp_path, "viewer_rooms.png")
    assert page.problems() == [], f"Studio reported problems (screenshot {path})"
    assert page.exceptions == [], f"uncaught exceptions in the page (screenshot {path})"


@needs_viewer
def test_studio_follows_the_live_view_on_the_simulated_clock(tmp_path, serve, browser):
    # Studio 1.48 offers only the subprotocol foxglove.websocket.v1: it reaches the
    # server through the shim, and its clock is the simulated time of the messages
    t0 = time.monotonic()
    stop = threading.Event()
    with LiveServer(port=0) as server:
        server.channel(
            "/metrics",
            "densityloop.Metrics",
            "jsonschema",
            json.dumps(METRICS_SCHEMA).encode(),
            "json",
        )

        def publish() -> None:
            for step in range(int(LOAD_S / 0.05)):  # bounded: 0.05 s a step
                if stop.is_set():
                    return
                t = 5.0 + 0.01 * step
                payload = {key: None for key in METRIC_KEYS}
                payload.update({key: 1.0 / (1.0 + t) for key in ALWAYS_NUMBERS}, t=t)
                server.publish("/metrics", round(t * 1e9), json.dumps(payload).encode())
                time.sleep(0.05)

        publisher = threading.Thread(target=publish, daemon=True)
        publisher.start()
        base = serve({"/layout.json": LAYOUT})
        page = browser(
            f"{base}/index.html?ds=foxglove-websocket&ds.url={server.url}"
            f"&dl.layout={base}/layout.json&layoutId=densityloop"
        )
        start = re.compile(r"START TIME\n([0-9.]+)\n")
        try:
            page.wait_for(
                lambda: topic_listed(page.text(), "/metrics", "densityloop.Metrics"),
                "/metrics in the topic list",
            )
            page.wait_for(lambda: start.search(page.text()) is not None, "the start time")
            page.wait_for(lambda: LEGEND.search(page.text()) is not None, "a plotted live value")
        finally:
            stop.set()
            path = keep(page.screenshot(), tmp_path, "viewer_live.png")
        publisher.join(5)
        shown = float(start.search(page.text())[1])
    # seconds since the epoch of the simulated clock, not the wall clock (~1.8e9 s)
    assert 5.0 <= shown < 5.0 + LOAD_S, f"start time {shown} (screenshot {path})"
    assert page.problems() == [], f"Studio reported problems (screenshot {path})"
    assert page.exceptions == [], f"uncaught exceptions in the page (screenshot {path})"
    print(f"live viewer test wall time: {time.monotonic() - t0:.1f} s")
