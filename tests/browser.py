"""Headless Chromium driven over WebDriver (W3C, plain HTTP to Debian's chromedriver): the tests
of the web monitor and its benchmarks (``bench/_web.py``) watch the page through it.

Five requests are all the page's tests need (new session, go to a URL, run a script, take a
screenshot, end the session), so this speaks the protocol itself rather than pulling in a
client library. Each browser gets a fresh profile in a temporary directory and the flags that
keep Chromium off the network (no background networking, component updates or sync): the page
is served on loopback and needs nothing else.
"""

from __future__ import annotations

import base64
import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path
from types import TracebackType
from typing import Any

INSTALL = "sudo apt-get install chromium chromium-driver"
"""What a machine without the browser needs (Debian's packages; CI installs them)."""
CHROMIUM = ("chromium", "chromium-browser")
CHROMEDRIVER = "chromedriver"
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-dev-shm-usage",
    "--disable-breakpad",  # no crash handler: it would outlive the browser in a session of its own
    "--disable-crash-reporter",
)
START_TIMEOUT_S = 30.0  # a browser's start on a loaded machine
REQUEST_TIMEOUT_S = 120.0  # one command (a page load takes 50 s at load 30 on two cores)


def _naming(text: str) -> list[int]:
    """The live processes whose command line contains ``text`` (a zombie's is empty)."""
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            with contextlib.suppress(OSError):
                if text.encode() in (entry / "cmdline").read_bytes():
                    found.append(int(entry.name))
    return found


def find_browser() -> tuple[str, str] | None:
    """(chromium, chromedriver) on PATH, or None when either is missing."""
    browser = next((path for name in CHROMIUM if (path := shutil.which(name))), None)
    driver = shutil.which(CHROMEDRIVER)
    return None if browser is None or driver is None else (browser, driver)


class WebDriverError(RuntimeError):
    """chromedriver answered with an error (its message kept)."""


class Browser:
    """One chromedriver and the headless Chromium it runs; a context manager."""

    def __init__(self, width: int = 1200, height: int = 900) -> None:
        found = find_browser()
        if found is None:
            raise WebDriverError(f"no chromium and chromedriver: {INSTALL}")
        browser, driver = found
        # A browser still writing its profile as it is stopped must not fail the cleanup.
        self._profile = tempfile.TemporaryDirectory(
            prefix="esc-bridge-chromium-", ignore_cleanup_errors=True
        )
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            port = sock.getsockname()[1]
        self._base = f"http://127.0.0.1:{port}"
        # A process group of its own, which Chromium's processes join: close() ends them all,
        # however the session went. Chromium's crash handlers leave the group (they daemonize)
        # and keep their database under the configuration directory: set to the temporary
        # one, it names that directory in their command lines too, where close() finds them.
        self.driver = subprocess.Popen(
            [driver, f"--port={port}"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
            env={**os.environ, "XDG_CONFIG_HOME": self._profile.name},
        )
        self.session = ""
        self._closed = False
        try:
            self._wait_for_driver()
            options = {
                "binary": browser,
                "args": [
                    *CHROMIUM_FLAGS,
                    f"--user-data-dir={Path(self._profile.name) / 'profile'}",
                    f"--window-size={width},{height}",
                ],
            }
            # "eager": get() returns once the document is parsed; the tests wait for what they
            # look for themselves.
            capabilities = {
                "browserName": "chrome",
                "pageLoadStrategy": "eager",
                "goog:chromeOptions": options,
            }
            answer = self._request(
                "POST", "/session", {"capabilities": {"alwaysMatch": capabilities}}
            )
            self.session = answer["sessionId"]
        except BaseException:
            self.close()
            raise

    def _wait_for_driver(self) -> None:
        deadline = time.monotonic() + START_TIMEOUT_S
        while True:
            try:
                self._request("GET", "/status")
                return
            except (OSError, WebDriverError):
                if time.monotonic() > deadline or self.driver.poll() is not None:
                    raise
                time.sleep(0.05)

    def _request(self, method: str, path: str, body: Any = None) -> Any:
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(
            self._base + path,
            data=data,
            method=method,
            headers={"Content-Type": "application/json"},
        )
        try:
            with urllib.request.urlopen(request, timeout=REQUEST_TIMEOUT_S) as answer:
                return json.loads(answer.read())["value"]
        except urllib.error.HTTPError as exc:
            raise WebDriverError(
                f"{method} {path}: {exc.read().decode(errors='replace')}"
            ) from None

    def _session(self, method: str, path: str, body: Any = None) -> Any:
        return self._request(method, f"/session/{self.session}{path}", body)

    def get(self, url: str) -> None:
        """Load ``url`` (returns once its document is parsed)."""
        self._session("POST", "/url", {"url": url})

    def run(self, script: str, *args: Any) -> Any:
        """Run ``script`` (a function body; ``arguments`` holds ``args``) in the page; what it
        returns."""
        return self._session("POST", "/execute/sync", {"script": script, "args": list(args)})

    def wait_for(self, script: str, timeout_s: float, *args: Any) -> Any:
        """Run ``script`` until it returns something truthy; that value.

        Raises:
            AssertionError: it did not within ``timeout_s`` (its last value named).
        """
        deadline = time.monotonic() + timeout_s
        value = None
        while time.monotonic() < deadline:
            value = self.run(script, *args)
            if value:
                return value
            time.sleep(0.1)
        raise AssertionError(f"not true within {timeout_s} s: {script!r} gave {value!r}")

    def screenshot(self, path: Path) -> None:
        """The window as a PNG."""
        path.write_bytes(base64.b64decode(self._session("GET", "/screenshot")))

    def set_window(self, width: int, height: int) -> None:
        self._session("POST", "/window/rect", {"width": width, "height": height})

    def close(self) -> None:
        """End the session, the browser and the driver; a second call does nothing."""
        if self._closed:
            return
        self._closed = True
        if self.session:
            with contextlib.suppress(OSError, WebDriverError):
                self._request("DELETE", f"/session/{self.session}")
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.driver.pid, signal.SIGTERM)
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.driver.wait(10)
        with contextlib.suppress(ProcessLookupError):  # whatever of Chromium is still there
            os.killpg(self.driver.pid, signal.SIGKILL)
        self.driver.wait()
        self._end_strays()
        self._profile.cleanup()

    def _end_strays(self) -> None:
        """Kill every process still naming the temporary directory (the crash handlers, which
        left the group) and wait until none is left."""
        deadline = time.monotonic() + START_TIMEOUT_S
        while strays := _naming(self._profile.name):
            if time.monotonic() > deadline:
                raise WebDriverError(f"Chromium's processes {strays} outlived SIGKILL")
            for pid in strays:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.kill(pid, signal.SIGKILL)
            time.sleep(0.05)

    def __enter__(self) -> Browser:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
