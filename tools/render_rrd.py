"""Render a Rerun recording the way a user sees it: the Rerun web viewer in headless Chromium.

    python tools/render_rrd.py RECORDING.rrd [--out DIR] [--size 1600x1000] [--timeout 180]

Starts the venv's ``rerun`` serving RECORDING to its web viewer (127.0.0.1 only, free
ports), opens the viewer in headless Chromium with WebGL in software (SwiftShader), waits
until the picture stops changing (the recording has loaded and been drawn: the same
screenshot ``--settle`` times in a row, polled every ``--poll`` s) and saves it as
``DIR/<recording stem>.png``. Prints one JSON line: the PNG path, the seconds from opening
the page until the picture settled (``loaded_s``: the web viewer's open time, including the
download and start of the viewer itself) and the total.

Chromium is driven through the DevTools protocol over a websocket (the ``websockets``
package); it runs with a fresh profile and no network besides 127.0.0.1. Needs Chromium
(``chromium`` or ``chromium-browser`` or ``google-chrome`` on PATH, or ``CHROMIUM``).
Every process started here is stopped before the script exits.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import hashlib
import importlib.util
import itertools
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any
from urllib.parse import quote

from rra_agent.bus.config import free_port

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
CHROMIUM_FLAGS = (
    "--headless=new",
    "--no-sandbox",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--disable-quic",
    "--disable-extensions",
    "--disable-default-apps",
    "--hide-scrollbars",
    "--mute-audio",
    # WebGL without a GPU: ANGLE on SwiftShader.
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--ignore-gpu-blocklist",
)


class RenderError(Exception):
    """The recording could not be rendered (message: what and why)."""


def find_chromium() -> str | None:
    """The Chromium executable (``CHROMIUM`` first, then PATH), or None."""
    override = os.environ.get("CHROMIUM")
    if override:
        return override
    for name in CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return found
    return None


def _stop(proc: subprocess.Popen[bytes] | None) -> None:
    """SIGTERM the process group, SIGKILL it after 5 s; reap."""
    if proc is None or proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    except ProcessLookupError:
        pass


def _wait_http(url: str, deadline: float, proc: subprocess.Popen[bytes], what: str) -> bytes:
    """GET ``url`` until it answers (RenderError if ``proc`` dies or the deadline passes)."""
    while True:
        try:
            with urllib.request.urlopen(url, timeout=2) as r:
                return r.read()
        except OSError:
            if proc.poll() is not None:
                raise RenderError(f"{what} exited with status {proc.returncode}") from None
            if time.monotonic() > deadline:
                raise RenderError(f"{what} did not answer at {url}") from None
            time.sleep(0.1)


class Cdp:
    """A minimal Chrome DevTools protocol client (one page target, synchronous calls)."""

    def __init__(self, ws_url: str) -> None:
        from websockets.sync.client import connect

        self.stack = contextlib.ExitStack()
        self.ws = self.stack.enter_context(connect(ws_url, max_size=None, open_timeout=10))
        self.ids = itertools.count(1)

    def call(self, method: str, timeout: float = 60.0, **params: Any) -> dict[str, Any]:
        n = next(self.ids)
        self.ws.send(json.dumps({"id": n, "method": method, "params": params}))
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise RenderError(f"DevTools {method} timed out")
            msg = json.loads(self.ws.recv(timeout=left))
            if msg.get("id") == n:
                if "error" in msg:
                    raise RenderError(f"DevTools {method}: {msg['error'].get('message')}")
                return msg.get("result", {})

    def close(self) -> None:
        self.stack.close()


def render(
    rrd: Path,
    out: Path,
    *,
    size: tuple[int, int] = (1600, 1000),
    timeout: float = 180.0,
    poll: float = 1.0,
    settle: int = 4,
) -> dict[str, Any]:
    """Render ``rrd`` into the PNG ``out``; returns what was measured."""
    from rra_agent.cli.view import rerun_binary

    chromium = find_chromium()
    if chromium is None:
        raise RenderError("no Chromium found (apt-get install chromium, or set CHROMIUM)")
    if importlib.util.find_spec("websockets") is None:
        raise RenderError("the websockets package is missing (pip install websockets)")
    rrd = rrd.resolve()
    if not rrd.is_file():
        raise RenderError(f"{rrd}: no such recording")
    started = time.monotonic()
    deadline = started + timeout
    web, grpc = free_port(), free_port()
    env = {**os.environ, "RERUN_ANALYTICS": "0", "BROWSER": "/bin/true"}
    viewer_cmd = [
        rerun_binary(), str(rrd), "--web-viewer", "--bind", "127.0.0.1",
        "--web-viewer-port", str(web), "--port", str(grpc), "--renderer", "webgl",
    ]  # fmt: skip
    viewer = browser = None
    cdp: Cdp | None = None
    profile = tempfile.mkdtemp(prefix="rra-render-")
    try:
        viewer = subprocess.Popen(
            viewer_cmd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL, start_new_session=True,
        )  # fmt: skip
        _wait_http(f"http://127.0.0.1:{web}/", deadline, viewer, "the rerun web viewer")
        browser = subprocess.Popen(
            [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
             "--remote-debugging-address=127.0.0.1", "--remote-debugging-port=0",
             f"--window-size={size[0]},{size[1]}", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
            start_new_session=True,
        )  # fmt: skip
        port_file = Path(profile) / "DevToolsActivePort"
        while not port_file.is_file() or not port_file.read_text().strip():
            if browser.poll() is not None:
                raise RenderError(f"chromium exited with status {browser.returncode}")
            if time.monotonic() > deadline:
                raise RenderError("chromium did not open its DevTools port")
            time.sleep(0.1)
        devtools = int(port_file.read_text().split()[0])
        targets = json.loads(
            _wait_http(f"http://127.0.0.1:{devtools}/json/list", deadline, browser, "chromium")
        )
        page = next(t for t in targets if t.get("type") == "page")
        cdp = Cdp(page["webSocketDebuggerUrl"])
        cdp.call("Page.enable")
        cdp.call(
            "Emulation.setDeviceMetricsOverride",
            width=size[0], height=size[1], deviceScaleFactor=1, mobile=False,
        )  # fmt: skip
        source = quote(f"rerun+http://127.0.0.1:{grpc}/proxy", safe="")
        url = f"http://127.0.0.1:{web}/?url={source}&renderer=webgl"
        opened = time.monotonic()
        cdp.call("Page.navigate", url=url)
        last, same, first_same, shot = "", 0, opened, b""
        while True:
            if time.monotonic() > deadline:
                raise RenderError(f"the picture did not settle within {timeout:g} s")
            time.sleep(poll)  # sampling period of the picture, not a synchronisation
            shot = base64.b64decode(cdp.call("Page.captureScreenshot", format="png")["data"])
            digest = hashlib.sha256(shot).hexdigest()
            if digest == last:
                same += 1
            else:
                last, same, first_same = digest, 0, time.monotonic()
            # A blank page is small: require a picture with content before trusting it.
            if same >= settle - 1 and len(shot) > 20_000:
                break
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(shot)
        return {
            "png": str(out),
            "recording": str(rrd),
            "recording_bytes": rrd.stat().st_size,
            "loaded_s": round(first_same - opened, 1),
            "total_s": round(time.monotonic() - started, 1),
        }
    finally:
        if cdp is not None:
            cdp.close()
        _stop(browser)
        _stop(viewer)
        shutil.rmtree(profile, ignore_errors=True)


def _size(text: str) -> tuple[int, int]:
    w, _, h = text.partition("x")
    return int(w), int(h)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("recording", type=Path, help="the .rrd file")
    p.add_argument("--out", type=Path, default=Path("/tmp/rra-screens"), help="PNG folder")
    p.add_argument("--name", help="PNG file name without .png (default: the recording's stem)")
    p.add_argument("--size", type=_size, default=(1600, 1000), help="WIDTHxHEIGHT")
    p.add_argument("--timeout", type=float, default=180.0, help="give up after this (s)")
    p.add_argument("--poll", type=float, default=1.0, help="seconds between screenshots")
    p.add_argument("--settle", type=int, default=4, help="identical screenshots in a row")
    args = p.parse_args(argv)
    out = args.out / f"{args.name or args.recording.stem}.png"
    try:
        result = render(
            args.recording, out, size=args.size, timeout=args.timeout, poll=args.poll,
            settle=args.settle,
        )  # fmt: skip
    except RenderError as e:
        print(f"render_rrd: {e}", file=sys.stderr)
        return 1
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
