"""Headless Chromium for the playground's tests: Debian's chromium driven through chromium-driver by Selenium."""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

CHROMIUM = ("/usr/bin/chromium", "/usr/bin/chromium-browser")
DRIVER = ("/usr/bin/chromedriver", "/usr/lib/chromium/chromedriver")


def _first(paths: tuple[str, ...], name: str) -> str:
    for p in paths:
        if Path(p).exists():
            return p
    found = shutil.which(name)
    if found is None:
        pytest.fail(f"{name} is not installed: bash .ci/setup installs Debian's chromium and chromium-driver")
    return found


@contextmanager
def chromium(downloads: Path, width: int = 1400, height: int = 1000) -> Iterator:
    """A headless Chromium that saves downloads into `downloads`."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = _first(CHROMIUM, "chromium")
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                f"--window-size={width},{height}"):
        opts.add_argument(arg)
    opts.add_experimental_option("prefs", {"download.default_directory": str(downloads),
                                           "download.prompt_for_download": False})
    driver = webdriver.Chrome(service=Service(_first(DRIVER, "chromedriver")), options=opts)
    driver.set_page_load_timeout(60)
    try:
        yield driver
    finally:
        driver.quit()


def set_value(driver, element_id: str, value) -> None:
    """Set an input's value as typing would, firing its input and change events."""
    driver.execute_script(
        "const e = document.getElementById(arguments[0]); e.value = arguments[1];"
        "e.dispatchEvent(new Event('input', {bubbles: true})); e.dispatchEvent(new Event('change', {bubbles: true}));",
        element_id, str(value))


def wait(pred, timeout: float, what: str, interval: float = 0.1):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = pred()
        if got:
            return got
        time.sleep(interval)
    raise TimeoutError(f"timed out after {timeout} s waiting for {what}")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def shot(driver, name: str) -> None:
    """With SEASYNTH_SCREENSHOTS=DIR, the page as DIR/NAME.png, in 256 colours to stay small."""
    from PIL import Image

    folder = os.environ.get("SEASYNTH_SCREENSHOTS")
    if folder:
        path = Path(folder) / f"{name}.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(str(path))
        Image.open(path).convert("RGB").quantize(256, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE).save(
            path, optimize=True)  # (median cut, the default, loses a small box's colour)


def status(driver) -> str:
    return driver.find_element("id", "status").text


def preview_src(driver) -> str:
    return driver.find_element("id", "preview-image").get_attribute("src") or ""


def server_preview(base: str, spec: dict, frame: int = 0, headers: dict | None = None) -> dict:
    """The preview the server renders for `spec` (no views), as the page would get it; a busy renderer (503, the
    page's own render holding the slot) is waited out, as the page does."""
    body = {"spec": spec, "frame": frame, "views": []}
    r = wait(lambda: (r := httpx.post(base + "/playground/preview", json=body, headers=headers, timeout=60))
             .status_code != 503 and r, 120, "a free render slot")
    assert r.status_code == 200, r.text
    return r.json()


def page_spec(driver) -> dict:
    return driver.execute_script("return spec;")


@contextmanager
def playground_server(spec: Path, port: int, out: Path, log: Path) -> Iterator[str]:
    """`seasynth playground SPEC` in a child process; yields its base URL once the page answers."""
    with open(log, "wb") as sink:
        proc = subprocess.Popen([sys.executable, "-m", "seasynth.cli", "playground", str(spec), "--no-browser",
                                 "--port", str(port), "--out", str(out)], stdout=sink, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        def up():
            if proc.poll() is not None:
                raise RuntimeError(f"seasynth playground exited {proc.returncode}:\n{log.read_text()}")
            try:
                return httpx.get(base + "/playground/config", timeout=2).status_code == 200
            except httpx.HTTPError:
                return False
        wait(up, 90, "seasynth playground to answer", interval=0.25)
        yield base
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()


@contextmanager
def prefix_proxy(upstream: str, prefix: str) -> Iterator[tuple[str, list[str]]]:
    """A reverse proxy on loopback that serves `upstream` under `prefix` ("/site"), as an ingress mounting the API
    at a path would. Yields its base URL (prefix included) and the list of every path it was asked for (those
    outside the prefix answered 404)."""
    import threading
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    asked: list[str] = []
    hop = {"connection", "keep-alive", "transfer-encoding", "content-length", "content-encoding", "host"}

    class Handler(BaseHTTPRequestHandler):
        def _forward(self) -> None:
            asked.append(self.path)
            if not self.path.startswith(prefix + "/"):
                self.send_error(404)
                return
            body = self.rfile.read(int(self.headers.get("Content-Length") or 0))
            headers = {k: v for k, v in self.headers.items() if k.lower() not in hop}
            r = httpx.request(self.command, upstream + self.path[len(prefix):], headers=headers, content=body,
                              timeout=120)
            self.send_response(r.status_code)
            for k, v in r.headers.items():
                if k.lower() not in hop:
                    self.send_header(k, v)
            self.send_header("Content-Length", str(len(r.content)))
            self.end_headers()
            self.wfile.write(r.content)

        do_GET = do_POST = do_PUT = do_DELETE = _forward

        def log_message(self, *args) -> None:
            pass

    server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}{prefix}", asked
    finally:
        server.shutdown()
        server.server_close()
