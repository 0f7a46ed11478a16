"""A headless Chromium driven over the DevTools protocol, for larc view's browser test.

Why not ``chromium --screenshot --virtual-time-budget=...``: virtual time waits for page loads and
fetches but not for websocket messages, and viser sends the scene (the robot's meshes, the boxes,
the GUI) over a websocket in real time. Once the page is idle, virtual time runs ahead, so on a
slow or loaded machine (CI, twice: the robot at 21 orange pixels, whatever the budget) the
screenshot came before the meshes. Here the page runs in real time and screenshots are taken
until the caller's condition holds or a real-time deadline passes.

Proxies are bypassed on purpose (``ProxyHandler({})``, ``proxy=None``): every connection is to
127.0.0.1, and a proxy set in the environment must not intercept it.
"""

from __future__ import annotations

import base64
import json
import socket
import subprocess
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager

_DIRECT = urllib.request.build_opener(urllib.request.ProxyHandler({}))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _page_socket_url(port: int, deadline: float) -> str:
    """The DevTools websocket of the browser's first page, once the browser answers."""
    last = None
    while time.monotonic() < deadline:
        try:
            with _DIRECT.open(f"http://127.0.0.1:{port}/json/list", timeout=5) as r:
                pages = [t for t in json.load(r) if t.get("type") == "page"]
            if pages:
                return pages[0]["webSocketDebuggerUrl"]
        except OSError as e:  # not listening yet
            last = e
        time.sleep(0.25)
    raise TimeoutError(f"chromium's DevTools on port {port} did not answer ({last})")


@contextmanager
def chromium_page(chromium: str, url: str, width: int, height: int, *, start_timeout_s: float = 60.0):
    """Open ``url`` in a headless Chromium (software WebGL; every host but 127.0.0.1 resolves to
    nothing, so the page must be served whole locally). Yields ``shoot()``, which returns a PNG
    screenshot of the page as it is now."""
    from websockets.sync.client import connect

    port = free_port()
    with tempfile.TemporaryDirectory() as profile:
        p = subprocess.Popen([chromium, "--headless", "--no-sandbox", "--disable-gpu-sandbox", "--use-angle=swiftshader",
                              "--enable-unsafe-swiftshader", "--no-first-run", "--disable-background-networking",
                              "--disable-component-update", "--disable-sync",
                              "--host-resolver-rules=MAP * ~NOTFOUND, EXCLUDE 127.0.0.1",
                              f"--remote-debugging-port={port}", f"--user-data-dir={profile}",
                              f"--window-size={width},{height}", url],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            ws_url = _page_socket_url(port, time.monotonic() + start_timeout_s)
            with connect(ws_url, max_size=None, proxy=None, open_timeout=start_timeout_s) as ws:
                ids = iter(range(1, 1 << 30))

                def call(method: str, **params) -> dict:
                    i = next(ids)
                    ws.send(json.dumps({"id": i, "method": method, "params": params}))
                    while True:  # skip events; the answer carries our id
                        msg = json.loads(ws.recv(timeout=120))
                        if msg.get("id") == i:
                            if "error" in msg:
                                raise RuntimeError(f"{method}: {msg['error']}")
                            return msg["result"]

                # The window's size includes its frame: the page's own size is set exactly.
                call("Emulation.setDeviceMetricsOverride", width=width, height=height, deviceScaleFactor=1,
                     mobile=False)
                yield lambda: base64.b64decode(call("Page.captureScreenshot", format="png")["data"])
        finally:
            p.kill()
            p.wait(timeout=30)


def screenshots(shoot, *, timeout_s: float, every_s: float = 1.0) -> Iterator[bytes]:
    """Screenshots from ``shoot`` every ``every_s`` seconds of real time until ``timeout_s`` has
    passed (at least one). The caller stops at the first that shows what it waits for."""
    deadline = time.monotonic() + timeout_s
    while True:
        yield shoot()
        if time.monotonic() >= deadline:
            return
        time.sleep(every_s)
