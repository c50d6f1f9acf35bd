"""A small headless-Chromium driver speaking the Chrome DevTools Protocol (no selenium).

    with Browser.launch(find_chromium(), tmp_path / "profile") as browser:
        page = browser.open(Path("report/index.html").resolve().as_uri())
        page.evaluate("document.title")
        page.errors          # console errors, uncaught exceptions, failed loads
        page.screenshot(tmp_path / "page.png")

Commands go over the browser's DevTools websocket with flattened target sessions, so
one connection drives the page and receives its events.
"""
from __future__ import annotations

import base64
import contextlib
import json
import os
import re
import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path
from urllib.parse import urlsplit

from websockets.sync.client import connect

BINARIES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable", "chrome")
DEVTOOLS_LINE = re.compile(r"DevTools listening on (ws://\S+)")


def find_chromium() -> str | None:
    """$CHROMIUM if set, else the first Chromium-like binary on PATH, else None."""
    if os.environ.get("CHROMIUM"):
        return shutil.which(os.environ["CHROMIUM"])
    return next((p for p in map(shutil.which, BINARIES) if p), None)


class CDPError(RuntimeError):
    pass


class Browser:
    def __init__(self, proc: subprocess.Popen, ws_url: str, log: list[str]):
        self.proc, self.log = proc, log
        # our own socket: a local endpoint must never go through an HTTP(S)_PROXY
        url = urlsplit(ws_url)
        sock = socket.create_connection((url.hostname, url.port), timeout=30)
        self._stack = contextlib.ExitStack()
        self.ws = self._stack.enter_context(connect(ws_url, sock=sock, max_size=None, open_timeout=30))
        self.events: list[dict] = []
        self._id = 0

    @classmethod
    def launch(cls, binary: str, profile_dir: Path, *, width: int = 1280, height: int = 900,
               timeout: float = 30.0) -> "Browser":
        proc = subprocess.Popen(
            [binary, "--headless=new", "--no-sandbox", "--disable-gpu", "--remote-debugging-port=0",
             f"--user-data-dir={profile_dir}", f"--window-size={width},{height}", "--no-first-run",
             "--no-default-browser-check", "--hide-scrollbars", "about:blank"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        log: list[str] = []
        found: list[str] = []
        ready = threading.Event()

        def drain():  # keep reading stderr so Chromium never blocks on a full pipe
            for line in proc.stderr:
                log.append(line.rstrip())
                m = DEVTOOLS_LINE.search(line)
                if m and not found:
                    found.append(m.group(1))
                    ready.set()
            ready.set()

        threading.Thread(target=drain, daemon=True).start()
        if not ready.wait(timeout) or not found:
            proc.kill()
            proc.wait()
            raise CDPError(f"{binary} printed no DevTools URL within {timeout:.0f} s:\n" + "\n".join(log[-20:]))
        return cls(proc, found[0], log)

    def send(self, method: str, params: dict | None = None, *, session: str | None = None,
             timeout: float = 30.0) -> dict:
        self._id += 1
        msg = {"id": self._id, "method": method, "params": params or {}}
        if session:
            msg["sessionId"] = session
        self.ws.send(json.dumps(msg))
        deadline = time.monotonic() + timeout
        while True:
            reply = self._recv(deadline, method)
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise CDPError(f"{method}: {reply['error'].get('message')}")
                return reply.get("result", {})
            self.events.append(reply)

    def wait_for(self, method: str, *, session: str | None = None, after: int = 0,
                 timeout: float = 30.0) -> dict:
        """The first event `method` (of `session`) received at or after index `after`."""
        deadline = time.monotonic() + timeout
        i = after
        while True:
            while i < len(self.events):
                e = self.events[i]
                i += 1
                if e.get("method") == method and (session is None or e.get("sessionId") == session):
                    return e.get("params", {})
            self.events.append(self._recv(deadline, method))

    def _recv(self, deadline: float, what: str) -> dict:
        left = deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError(f"no answer to {what} in time")
        try:
            return json.loads(self.ws.recv(timeout=left))
        except TimeoutError:
            raise TimeoutError(f"no answer to {what} in time") from None

    def open(self, url: str, *, timeout: float = 30.0) -> "Page":
        """A new tab showing `url`, once its load event fired."""
        target = self.send("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = self.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        page = Page(self, session)
        for domain in ("Runtime", "Log", "Page"):
            self.send(f"{domain}.enable", session=session)
        mark = len(self.events)
        reply = self.send("Page.navigate", {"url": url}, session=session, timeout=timeout)
        if reply.get("errorText"):
            raise CDPError(f"cannot open {url}: {reply['errorText']}")
        self.wait_for("Page.loadEventFired", session=session, after=mark, timeout=timeout)
        return page

    def close(self) -> None:
        try:
            self.send("Browser.close", timeout=5)
        except Exception:  # the browser may close the socket before answering
            pass
        try:
            self._stack.close()
        finally:
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class Page:
    def __init__(self, browser: Browser, session: str):
        self.browser, self.session = browser, session

    def send(self, method: str, params: dict | None = None, timeout: float = 30.0) -> dict:
        return self.browser.send(method, params, session=self.session, timeout=timeout)

    def evaluate(self, expression: str, timeout: float = 30.0):
        """The JSON value of a JavaScript expression (promises are awaited)."""
        out = self.send("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                             "awaitPromise": True}, timeout)
        if "exceptionDetails" in out:
            d = out["exceptionDetails"]
            raise CDPError(f"evaluate failed: {d.get('exception', {}).get('description') or d.get('text')}")
        return out["result"].get("value")

    @property
    def errors(self) -> list[str]:
        """Uncaught exceptions, console.error calls and error log entries (failed loads)."""
        out = []
        for e in self.browser.events:
            if e.get("sessionId") != self.session:
                continue
            p = e.get("params", {})
            if e["method"] == "Runtime.exceptionThrown":
                d = p.get("exceptionDetails", {})
                out.append(f"exception: {d.get('exception', {}).get('description') or d.get('text')}")
            elif e["method"] == "Runtime.consoleAPICalled" and p.get("type") == "error":
                out.append("console.error: " + " ".join(str(a.get("value", a.get("description")))
                                                        for a in p.get("args", [])))
            elif e["method"] == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
                entry = p["entry"]
                out.append(f"log: {entry.get('text')} {entry.get('url', '')}".strip())
        return out

    def screenshot(self, path: Path, *, max_height: int = 6000) -> Path:
        """A PNG of the whole page (up to `max_height` CSS pixels)."""
        size = self.send("Page.getLayoutMetrics")["cssContentSize"]
        clip = {"x": 0, "y": 0, "width": size["width"], "height": min(size["height"], max_height), "scale": 1}
        shot = self.send("Page.captureScreenshot", {"format": "png", "clip": clip,
                                                    "captureBeyondViewport": True}, timeout=60)
        path = Path(path)
        path.write_bytes(base64.b64decode(shot["data"]))
        return path
