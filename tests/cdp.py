"""Headless Chromium driven over the DevTools protocol, for the browser test.

Only the standard library: Chromium is started with ``--remote-debugging-port=0``, a page
target is opened over its HTTP endpoint, and JavaScript is evaluated in it over a WebSocket
(RFC 6455, text frames, the client masking what it sends). ``chromium()`` finds the binary
(Debian's ``chromium``, which ``.ci/run`` installs when it is missing).
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import re
import shutil
import socket
import struct
import subprocess
import tempfile
import threading
import time
import urllib.parse
import urllib.request
from collections.abc import Iterator
from typing import Any

#: no proxy: the browser and the dashboard are on this machine
OPENER = urllib.request.build_opener(urllib.request.ProxyHandler({}))


def stop(process: subprocess.Popen) -> None:
    """End a server or browser process: SIGTERM, then SIGKILL after 15 s."""
    process.terminate()
    try:
        process.wait(timeout=15)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


def chromium() -> str | None:
    """The Chromium binary on PATH, or None."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if found := shutil.which(name):
            return found
    return None


class Page:
    """One browser tab: ``goto`` a URL, ``evaluate`` JavaScript (awaiting promises)."""

    def __init__(self, websocket_url: str) -> None:
        parts = urllib.parse.urlsplit(websocket_url)
        self._socket = socket.create_connection((parts.hostname, parts.port), timeout=60)
        key = base64.b64encode(os.urandom(16)).decode()
        request = (
            f"GET {parts.path} HTTP/1.1\r\nHost: {parts.netloc}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
        )
        self._socket.sendall(request.encode())
        response = b""
        while b"\r\n\r\n" not in response:
            chunk = self._socket.recv(4096)
            if not chunk:
                raise ConnectionError("the browser closed the DevTools connection")
            response += chunk
        head, self._buffer = response.split(b"\r\n\r\n", 1)
        if b" 101 " not in head.split(b"\r\n", 1)[0]:
            raise ConnectionError(f"no WebSocket upgrade: {head[:200]!r}")
        self._next_id = 0

    def close(self) -> None:
        self._socket.close()

    def _send(self, text: str) -> None:
        payload = text.encode()
        header = bytes([0x81])  # FIN, text frame
        size = len(payload)
        if size < 126:
            header += bytes([0x80 | size])
        elif size < 1 << 16:
            header += bytes([0x80 | 126]) + struct.pack(">H", size)
        else:
            header += bytes([0x80 | 127]) + struct.pack(">Q", size)
        mask = os.urandom(4)
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        self._socket.sendall(header + mask + masked)

    def _read(self, count: int) -> bytes:
        while len(self._buffer) < count:
            chunk = self._socket.recv(65536)
            if not chunk:
                raise ConnectionError("the browser closed the DevTools connection")
            self._buffer += chunk
        data, self._buffer = self._buffer[:count], self._buffer[count:]
        return data

    def _receive(self) -> str:
        """One whole message (continuation frames joined); control frames skipped."""
        message = b""
        while True:
            first, second = self._read(2)
            size = second & 0x7F
            if size == 126:
                size = struct.unpack(">H", self._read(2))[0]
            elif size == 127:
                size = struct.unpack(">Q", self._read(8))[0]
            payload = self._read(size)  # the server does not mask
            opcode = first & 0x0F
            if opcode >= 0x8:  # close, ping, pong
                if opcode == 0x8:
                    raise ConnectionError("the browser closed the DevTools connection")
                continue
            message += payload
            if first & 0x80:
                return message.decode()

    def call(self, method: str, **params: Any) -> dict[str, Any]:
        """A DevTools command and its result (events arriving meanwhile are dropped)."""
        self._next_id += 1
        self._send(json.dumps({"id": self._next_id, "method": method, "params": params}))
        while True:
            reply = json.loads(self._receive())
            if reply.get("id") == self._next_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def evaluate(self, expression: str) -> Any:
        """The JSON value of a JavaScript expression (a promise is awaited)."""
        result = self.call(
            "Runtime.evaluate", expression=expression, awaitPromise=True, returnByValue=True
        )
        if "exceptionDetails" in result:
            raise RuntimeError(f"JavaScript failed: {result['exceptionDetails']}")
        return result["result"].get("value")

    def goto(self, url: str) -> None:
        self.call("Page.navigate", url=url)

    def wait_for(self, expression: str, timeout: float = 30) -> Any:
        """Evaluate ``expression`` until it is truthy, and return it; while the page is
        still loading it may throw (no ``document.body`` yet), which counts as not yet."""
        deadline = time.monotonic() + timeout
        error = None
        while True:
            try:
                value = self.evaluate(expression)
            except RuntimeError as e:
                value, error = None, e
            if value:
                return value
            if time.monotonic() > deadline:
                raise AssertionError(
                    f"timed out after {timeout} s waiting for {expression} (last error: {error})"
                )
            time.sleep(0.2)


@contextlib.contextmanager
def browser(width: int = 1600, height: int = 1200) -> Iterator[Page]:
    """Headless Chromium with one page, closed afterwards."""
    binary = chromium()
    if binary is None:
        raise RuntimeError("no chromium on PATH (Debian: apt-get install -y chromium)")
    profile = tempfile.mkdtemp(prefix="sweeper-chromium-")
    command = [
        binary,
        "--headless",
        "--no-sandbox",  # CI runs as root
        "--disable-gpu",
        "--no-first-run",
        "--mute-audio",
        "--autoplay-policy=no-user-gesture-required",
        "--remote-debugging-address=127.0.0.1",
        "--remote-debugging-port=0",
        f"--user-data-dir={profile}",
        f"--window-size={width},{height}",
        "about:blank",
    ]
    process = subprocess.Popen(
        command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    page = None
    try:
        deadline = time.monotonic() + 60
        port = None
        while port is None:
            line = process.stderr.readline()
            if not line and process.poll() is not None:
                raise RuntimeError(f"chromium exited with {process.returncode}")
            if match := re.search(r"DevTools listening on ws://[^:]+:(\d+)/", line):
                port = int(match[1])
            if time.monotonic() > deadline:
                raise RuntimeError("chromium did not say where DevTools listens")
        # keep reading its log, so that a full pipe never blocks the browser
        threading.Thread(target=process.stderr.read, daemon=True).start()
        new = f"http://127.0.0.1:{port}/json/new?about:blank"
        request = urllib.request.Request(new, method="PUT")
        with OPENER.open(request, timeout=30) as response:
            target = json.loads(response.read())
        page = Page(target["webSocketDebuggerUrl"])
        page.call("Page.enable")
        yield page
    finally:
        if page is not None:
            page.close()
        stop(process)
        shutil.rmtree(profile, ignore_errors=True)
