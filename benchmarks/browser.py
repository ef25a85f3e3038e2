"""The benchmark report in a real browser: headless Chromium over the DevTools protocol.

:class:`Chromium` opens a page in a real headless Chromium (Debian's ``chromium``) over the DevTools
protocol and reads back what it laid out and painted (plots, points, images, script errors, network
requests, a full-page screenshot): ``tests/test_report_browser.py`` checks ``report.html`` with it, and
:func:`write_screenshot` leaves ``report.png`` beside the page for readers without a browser.
"""

from __future__ import annotations

import json
import os
import queue
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

__all__ = ["Chromium", "PageView", "find_chromium", "write_screenshot", "CHROMIUM_ENV"]


#: Environment variable naming the Chromium (or Chrome) executable; otherwise the PATH is searched.
CHROMIUM_ENV = "STEREOTACTIP_CHROMIUM"
_CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable", "chrome")

# What the page looks like once laid out and painted, read in the page after its scripts ran: every
# trade-off plot (its data-* identity, its <svg> box, and each point's box, drawn colour, whether it is
# filled and whether the style leaves it shown), every image (loaded or broken) and the document's
# size. Boxes are in CSS pixels from the page's top left.
_INSPECT_JS = r"""(() => {
  const box = (el) => { const r = el.getBoundingClientRect();
    return {x: r.left + window.scrollX, y: r.top + window.scrollY, w: r.width, h: r.height}; };
  const plots = [...document.querySelectorAll('figure.plot')].map((f) => {
    const svg = f.querySelector('svg');
    const p = {ident: {...f.dataset}, svg: svg ? box(svg) : null, points: [], lines: 0};
    if (!svg) return p;
    p.lines = svg.querySelectorAll('polyline').length;
    for (const c of svg.querySelectorAll('circle')) {
      const st = getComputedStyle(c), t = c.querySelector('title');
      p.points.push({...box(c), colour: c.getAttribute('stroke'), filled: c.getAttribute('fill') !== 'none',
        shown: st.display !== 'none' && st.visibility === 'visible' && Number(st.opacity) > 0,
        tip: t ? t.textContent : ''});
    }
    return p;
  });
  const images = [...document.images].map((i) => ({src: i.getAttribute('src'),
    loaded: i.complete && i.naturalWidth > 0}));
  const d = document.documentElement;
  return {plots, images, width: Math.ceil(d.scrollWidth), height: Math.ceil(d.scrollHeight),
          title: document.title};
})()"""


def find_chromium() -> str | None:
    """The headless browser to use: ``$STEREOTACTIP_CHROMIUM`` if set, else the first Chromium/Chrome on
    the PATH (Debian: ``apt-get install chromium``); None when there is none."""
    import shutil

    named = os.environ.get(CHROMIUM_ENV)
    if named:
        return shutil.which(named) or (named if os.access(named, os.X_OK) else None)
    for name in _CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return found
    return None


@dataclass
class PageView:
    """One HTML file as headless Chromium laid it out, ran and painted it."""

    url: str
    plots: list[dict[str, Any]]          #: per ``figure.plot``: ``ident``, ``svg`` box, ``points``, ``lines``
    images: list[dict[str, Any]]         #: per ``<img>``: ``src``, ``loaded``
    errors: list[str]                    #: uncaught exceptions, console errors, failed loads, error log entries
    external: list[str]                  #: every URL requested that is not a local file or inline data
    width: int
    height: int
    png: bytes                           #: full-page screenshot, 1 image pixel per CSS pixel


class Chromium:
    """A headless Chromium driven over the Chrome DevTools protocol on a pipe (``--remote-debugging-pipe``:
    NUL-terminated JSON on file descriptors 3 and 4; no port, no extra Python package).

    Use as a context manager; :meth:`load` opens one file per call in a fresh tab with JavaScript on and
    every network URL blocked (a page that needs the network shows up in ``external`` and ``errors``)."""

    def __init__(self, executable: str | None = None, timeout_s: float = 90.0, width: int = 1200):
        import fcntl
        import subprocess
        import tempfile

        exe = executable or find_chromium()
        if exe is None:
            raise FileNotFoundError(f"no Chromium found: install it (Debian: apt-get install chromium) or set "
                                    f"{CHROMIUM_ENV} to its path")
        self.executable, self.timeout_s, self.width = exe, float(timeout_s), int(width)
        self._profile = tempfile.TemporaryDirectory(prefix="stereotactip-chromium-")
        self._log = open(Path(self._profile.name, "stderr.log"), "w+b")
        to_r, self._to_w = os.pipe()                # non-inheritable: the child sees only its own two ends
        self._from_r, from_w = os.pipe()
        # the child's ends moved to >= 10, so putting them on 3 and 4 in the child cannot clobber either
        child_r, child_w = fcntl.fcntl(to_r, fcntl.F_DUPFD, 10), fcntl.fcntl(from_w, fcntl.F_DUPFD, 10)
        os.close(to_r)
        os.close(from_w)

        def on_3_and_4() -> None:                   # runs in the child between fork and exec
            os.dup2(child_r, 3)
            os.dup2(child_w, 4)

        args = [exe, "--headless", "--remote-debugging-pipe", f"--user-data-dir={self._profile.name}",
                "--no-first-run", "--no-default-browser-check", "--disable-gpu", "--disable-extensions",
                "--disable-background-networking", "--disable-component-update", "--disable-sync",
                "--hide-scrollbars", "--mute-audio", "--force-device-scale-factor=1", "about:blank"]
        if hasattr(os, "geteuid") and os.geteuid() == 0:
            args.insert(1, "--no-sandbox")          # Chromium refuses to run its sandbox as root
        try:
            self._proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                          stderr=self._log, close_fds=False, preexec_fn=on_3_and_4)
        finally:
            os.close(child_r)
            os.close(child_w)
        self._inbox: queue.Queue = queue.Queue()
        self._events: list[dict[str, Any]] = []
        self._next_id = 0
        self._reader = threading.Thread(target=self._read, name="chromium-cdp", daemon=True)
        self._reader.start()
        self.version = self.call("Browser.getVersion").get("product", "?")

    # -- protocol ---------------------------------------------------------------------------------

    def _read(self) -> None:
        buf = b""
        while True:
            try:
                chunk = os.read(self._from_r, 1 << 16)
            except OSError:
                chunk = b""
            if not chunk:
                self._inbox.put(None)
                return
            buf += chunk
            *msgs, buf = buf.split(b"\0")
            for m in msgs:
                self._inbox.put(json.loads(m))

    def _stderr_tail(self) -> str:
        self._log.flush()
        self._log.seek(0)
        lines = self._log.read().decode("utf-8", "replace").splitlines()
        return "\n".join(line for line in lines[-8:] if "dbus" not in line) or "(nothing on stderr)"

    def call(self, method: str, params: Mapping[str, Any] | None = None, session: str | None = None) -> dict:
        """Send one command and wait for its result; events that arrive meanwhile are kept."""
        import time

        self._next_id += 1
        msg: dict[str, Any] = {"id": self._next_id, "method": method, "params": dict(params or {})}
        if session:
            msg["sessionId"] = session
        try:
            os.write(self._to_w, json.dumps(msg).encode() + b"\0")
        except OSError as exc:
            raise RuntimeError(f"Chromium ({self.executable}) is not running: {self._stderr_tail()}") from exc
        deadline = time.monotonic() + self.timeout_s
        while True:
            got = self._next(deadline, method)
            if got.get("id") == self._next_id:
                if "error" in got:
                    raise RuntimeError(f"Chromium: {method} failed: {got['error'].get('message')}")
                return got.get("result", {})
            self._events.append(got)

    def _next(self, deadline: float, what: str) -> dict:
        import time

        try:
            got = self._inbox.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            raise TimeoutError(f"Chromium did not answer {what} within {self.timeout_s:.0f} s") from None
        if got is None:
            raise RuntimeError(f"Chromium ({self.executable}) exited: {self._stderr_tail()}")
        return got

    def _wait_event(self, name: str, session: str, since: int) -> None:
        import time

        if any(e.get("method") == name and e.get("sessionId") == session for e in self._events[since:]):
            return
        deadline = time.monotonic() + self.timeout_s
        while True:
            got = self._next(deadline, name)
            self._events.append(got)
            if got.get("method") == name and got.get("sessionId") == session:
                return

    # -- pages ------------------------------------------------------------------------------------

    def load(self, html_path: Path | str) -> PageView:
        """Open ``html_path`` (a local file), let it load, run and paint, then read it back."""
        import base64

        path = Path(html_path).resolve()
        if not path.is_file():
            raise FileNotFoundError(f"no such HTML file: {path}")
        target = self.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        try:
            sid = self.call("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
            since = len(self._events)
            for domain in ("Page", "Runtime", "Log", "Network"):
                self.call(f"{domain}.enable", session=sid)
            self.call("Network.setBlockedURLs", {"urls": ["http://*", "https://*", "ws://*", "wss://*", "ftp://*"]},
                      session=sid)
            self.call("Emulation.setDeviceMetricsOverride", {"width": self.width, "height": 900,
                                                             "deviceScaleFactor": 1, "mobile": False}, session=sid)
            nav = self.call("Page.navigate", {"url": path.as_uri()}, session=sid)
            if nav.get("errorText"):
                raise RuntimeError(f"Chromium could not open {path}: {nav['errorText']}")
            self._wait_event("Page.loadEventFired", sid, since)
            # two animation frames after load: timers and handlers that run right after it have run too
            self._eval(sid, "new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))")
            info = self._eval(sid, _INSPECT_JS)
            w, h = max(1, int(info["width"])), max(1, min(int(info["height"]), 16384))
            shot = self.call("Page.captureScreenshot", {"format": "png", "captureBeyondViewport": True,
                                                        "clip": {"x": 0, "y": 0, "width": w, "height": h,
                                                                 "scale": 1}}, session=sid)
            self.call("Runtime.evaluate", {"expression": "0"}, session=sid)   # flush late events
            errors, external = self._page_problems(sid, since)
            return PageView(url=path.as_uri(), plots=info["plots"], images=info["images"], errors=errors,
                            external=external, width=w, height=h, png=base64.b64decode(shot["data"]))
        finally:
            self.call("Target.closeTarget", {"targetId": target})

    def _eval(self, sid: str, expression: str) -> Any:
        got = self.call("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                             "awaitPromise": True}, session=sid)
        if "exceptionDetails" in got:
            d = got["exceptionDetails"]
            raise RuntimeError(f"Chromium: inspecting the page failed: {d.get('exception', {}).get('description') or d.get('text')}")
        return got.get("result", {}).get("value")

    def _page_problems(self, sid: str, since: int) -> tuple[list[str], list[str]]:
        errors: list[str] = []
        external: list[str] = []
        urls: dict[str, str] = {}
        for e in self._events[since:]:
            if e.get("sessionId") != sid:
                continue
            m, p = e.get("method"), e.get("params", {})
            if m == "Runtime.exceptionThrown":
                d = p.get("exceptionDetails", {})
                errors.append("uncaught exception: " + str(d.get("exception", {}).get("description") or d.get("text")))
            elif m == "Runtime.consoleAPICalled" and p.get("type") in ("error", "assert"):
                errors.append(f"console.{p['type']}: " + " ".join(str(a.get("value", a.get("description", "")))
                                                                 for a in p.get("args", [])))
            elif m == "Log.entryAdded" and p.get("entry", {}).get("level") == "error":
                entry = p["entry"]
                errors.append(f"{entry.get('source', 'log')} error: {entry.get('text')} {entry.get('url', '')}".strip())
            elif m == "Network.requestWillBeSent":
                url = p.get("request", {}).get("url", "")
                urls[p.get("requestId", "")] = url
                if not url.startswith(("file:", "data:", "about:", "blob:")):
                    external.append(url)
            elif m == "Network.loadingFailed":
                errors.append(f"failed to load {urls.get(p.get('requestId', ''), '?')}: {p.get('errorText')}")
        return errors, external

    def close(self) -> None:
        import subprocess

        if getattr(self, "_proc", None) is not None and self._proc.poll() is None:
            try:
                self.call("Browser.close")
            except (RuntimeError, TimeoutError, OSError):
                pass
            try:
                self._proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait(timeout=10)
        for fd in (self._to_w, self._from_r):
            try:
                os.close(fd)
            except OSError:
                pass
        self._log.close()
        self._profile.cleanup()

    def __enter__(self) -> "Chromium":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def write_screenshot(html_path: Path | str, png_path: Path | str | None = None,
                     executable: str | None = None) -> Path | None:
    """A full-page PNG of ``html_path`` as headless Chromium paints it (default: beside it, ``.png``), for
    readers without a browser; None when no Chromium is found. Pages taller than 16384 px are cut there."""
    exe = executable or find_chromium()
    if exe is None:
        return None
    html_path = Path(html_path)
    png_path = Path(png_path) if png_path is not None else html_path.with_suffix(".png")
    with Chromium(exe) as browser:
        view = browser.load(html_path)
    from pipeline.io.atomic import atomic_write_bytes

    atomic_write_bytes(png_path, view.png)
    return png_path
