"""A headless Chromium driven over the W3C WebDriver protocol (plain HTTP + JSON to
``chromedriver``): no Python dependency beyond the standard library.

``chromium_missing()`` says why a browser test cannot run (None: it can): Debian's
``chromium`` and ``chromium-driver`` packages are needed (``HDMAP_TEST_CHROMIUM`` and
``HDMAP_TEST_CHROMEDRIVER`` name other binaries). ``chrome()``
starts ``chromedriver`` on a free port as a watched subprocess
(:func:`tests.support.processes.running`: it and the browsers it started are killed when
the block ends, also on failure), opens one browser session and deletes it at the end.
Every call has a timeout.
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import shutil
import time
import urllib.error
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from hdmap.ops.stack import free_port
from tests.support.processes import running

CHROMIUM = os.environ.get("HDMAP_TEST_CHROMIUM", "/usr/bin/chromium")
CHROMEDRIVER = os.environ.get("HDMAP_TEST_CHROMEDRIVER", "/usr/bin/chromedriver")
"""Debian's ``chromium`` and ``chromium-driver``; the environment variables point elsewhere."""
ARGS = (
    "--headless=new",
    "--no-sandbox",
    "--disable-gpu",
    "--use-angle=swiftshader",  # WebGL in software: MapLibre needs it, there is no GPU
    "--enable-unsafe-swiftshader",
    "--window-size=1400,900",
    "--disable-dev-shm-usage",
    "--no-first-run",
    "--disable-extensions",
    "--disable-background-networking",
)


def chromium_missing() -> str | None:
    """Why no browser test can run here, or None."""
    for path, pkg in ((CHROMIUM, "chromium"), (CHROMEDRIVER, "chromium-driver")):
        if shutil.which(path) is None:
            return f"{path} not found: apt-get install -y chromium chromium-driver (missing {pkg})"
    return None


class WebDriverError(RuntimeError):
    pass


def _call(method: str, url: str, body: Any = None, timeout: float = 60.0) -> Any:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, method=method)
    req.add_header("Content-Type", "application/json; charset=utf-8")
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return json.loads(r.read() or b"{}").get("value")
    except urllib.error.HTTPError as exc:
        try:
            value = json.loads(exc.read()).get("value", {})
            msg = f"{value.get('error')}: {value.get('message', '')[:2000]}"
        except (ValueError, AttributeError):
            msg = str(exc)
        raise WebDriverError(f"{method} {url}: {msg}") from None


class Browser:
    """One WebDriver session."""

    def __init__(self, driver_url: str, session_id: str):
        self.url = f"{driver_url}/session/{session_id}"

    def navigate(self, url: str) -> None:
        _call("POST", f"{self.url}/url", {"url": url})

    def execute(self, script: str, *args: Any) -> Any:
        """Run a function body in the page (``return ...``); its value."""
        return _call("POST", f"{self.url}/execute/sync", {"script": script, "args": list(args)})

    def execute_async(self, script: str, *args: Any) -> Any:
        """Run a function body whose last argument is the callback to call with the value."""
        return _call("POST", f"{self.url}/execute/async", {"script": script, "args": list(args)})

    def click_at(self, x: float, y: float) -> None:
        """A real mouse click at viewport coordinates (CSS pixels)."""
        actions = [
            {"type": "pointerMove", "duration": 0, "origin": "viewport", "x": int(x), "y": int(y)},
            {"type": "pointerDown", "button": 0},
            {"type": "pointerUp", "button": 0},
        ]
        body = {
            "actions": [
                {"type": "pointer", "id": "mouse", "parameters": {"pointerType": "mouse"},
                 "actions": actions}
            ]
        }  # fmt: skip
        _call("POST", f"{self.url}/actions", body)
        _call("DELETE", f"{self.url}/actions")

    def screenshot(self, path: Path) -> Path:
        png = base64.b64decode(_call("GET", f"{self.url}/screenshot"))
        path.write_bytes(png)
        return path

    def log(self) -> list[dict[str, Any]]:
        """The page's console messages so far (chromedriver's ``browser`` log)."""
        try:
            return _call("POST", f"{self.url}/se/log", {"type": "browser"}) or []
        except WebDriverError:
            return []


@contextlib.contextmanager
def chrome(log_dir: Path, startup_s: float = 30.0) -> Iterator[Browser]:
    """A headless Chromium session; chromedriver and the browser are stopped at the end."""
    port = free_port()
    driver_url = f"http://127.0.0.1:{port}"
    argv = [CHROMEDRIVER, f"--port={port}", f"--log-path={log_dir / 'chromedriver.log'}"]
    with running(argv, log_dir / "chromedriver.out") as proc:
        deadline = time.monotonic() + startup_s
        while True:
            with contextlib.suppress(OSError, WebDriverError, ValueError):
                if (_call("GET", f"{driver_url}/status", timeout=2.0) or {}).get("ready"):
                    break
            if proc.poll() is not None or time.monotonic() > deadline:
                raise WebDriverError(f"chromedriver did not start: see {log_dir}")
            time.sleep(0.1)
        caps = {
            "capabilities": {
                "alwaysMatch": {
                    "browserName": "chrome",
                    "goog:chromeOptions": {
                        "binary": CHROMIUM,
                        "args": [*ARGS, f"--user-data-dir={log_dir / 'chrome-profile'}"],
                    },
                    "goog:loggingPrefs": {"browser": "ALL"},
                    "timeouts": {"script": 30_000, "pageLoad": 60_000, "implicit": 0},
                }
            }
        }
        session = _call("POST", f"{driver_url}/session", caps, timeout=startup_s + 30)
        browser = Browser(driver_url, session["sessionId"])
        try:
            yield browser
        finally:
            with contextlib.suppress(OSError, WebDriverError):
                _call("DELETE", browser.url, timeout=20.0)
