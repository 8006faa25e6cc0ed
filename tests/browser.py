"""Helpers of the web console's browser tests: headless Chromium through its WebDriver,
screenshots a person can look at, and a Modbus TCP proxy that breaks a sensor.

Chromium and chromedriver are Debian's (scripts/setup-system.sh installs them);
as root Chromium needs ``--no-sandbox``.
"""

from __future__ import annotations

import os
import shutil
import socket
import struct
import threading
from pathlib import Path

import numpy as np
from matplotlib import image
from selenium import webdriver

ROOT = Path(__file__).resolve().parents[1]
SHOTS = ROOT / ".cache" / "screenshots" / "console"
DOCS_IMG = ROOT / "docs" / "img"
#: Set to 1 (``make screenshots``) to copy the documented screenshots into docs/img; a
#: plain test run leaves the tracked images alone, so a checkout stays clean.
UPDATE_DOCS_IMAGES = "SPINDLE_UPDATE_DOCS_IMAGES"


def chromium(
    width: int = 1500, height: int = 1000, capabilities: dict[str, object] | None = None
) -> webdriver.Chrome:
    """Headless Chromium; ``capabilities`` such as ``{"goog:loggingPrefs": {"performance":
    "ALL"}}`` (the DevTools network events, read with ``driver.get_log("performance")``)."""
    options = webdriver.ChromeOptions()
    for name, value in (capabilities or {}).items():
        options.set_capability(name, value)
    options.binary_location = shutil.which("chromium") or "/usr/bin/chromium"
    for argument in (
        "--headless=new",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--no-first-run",
        f"--window-size={width},{height}",
    ):
        options.add_argument(argument)
    if os.geteuid() == 0:
        options.add_argument("--no-sandbox")
    service = webdriver.ChromeService(shutil.which("chromedriver") or "/usr/bin/chromedriver")
    driver = webdriver.Chrome(options=options, service=service)
    driver.set_page_load_timeout(60)
    return driver


def screenshot(driver: webdriver.Chrome, name: str, docs_name: str | None = None) -> Path:
    """Save the page as ``.cache/screenshots/console/<name>.png`` and refuse a blank one.

    ``docs_name``: the docs/img file this screenshot illustrates; it is copied there only
    when ``SPINDLE_UPDATE_DOCS_IMAGES=1`` (``make screenshots``), never on a plain run.
    """
    SHOTS.mkdir(parents=True, exist_ok=True)
    path = SHOTS / f"{name}.png"
    height = driver.execute_script("return document.body.scrollHeight")
    driver.set_window_size(1500, min(max(int(height) + 150, 700), 4000))
    assert driver.save_screenshot(str(path)), path
    assert_not_blank(path)
    if docs_name is not None and os.environ.get(UPDATE_DOCS_IMAGES) == "1":
        DOCS_IMG.mkdir(parents=True, exist_ok=True)
        shutil.copy(path, DOCS_IMG / docs_name)
    return path


def assert_not_blank(path: Path) -> None:
    """A page's picture holds some ink (2 % of its pixels darker than light grey) and
    several colours: a white or single-colour page fails."""
    pixels = image.imread(path)[..., :3]
    ink = np.mean(np.any(pixels < 0.9, axis=-1))
    colours = len(np.unique((pixels * 15).astype(np.uint8).reshape(-1, 3), axis=0))
    assert ink > 0.02 and colours >= 8, (path, ink, colours)


class SensorBreakingProxy:
    """A Modbus TCP proxy in front of a transmitter server. While ``broken`` is set it
    answers the 16-register read of ``device_id`` with ``channel`` (0-based) open
    circuit: its status register 1 and its value register 32767, as a real module
    reports a broken Pt100."""

    def __init__(self, upstream_port: int, device_id: int = 1, channel: int = 2) -> None:
        self.upstream_port = upstream_port
        self.device_id = device_id
        self.channel = channel
        self.broken = threading.Event()
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.port = self._listener.getsockname()[1]
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self._listener.accept()
            except OSError:
                return
            upstream = socket.create_connection(("127.0.0.1", self.upstream_port))
            upstream.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            turn = threading.Semaphore(1)  # one request in flight, as on a serial line
            args = (client, upstream, turn)
            threading.Thread(target=self._requests, args=args, daemon=True).start()
            threading.Thread(target=self._answers, args=args, daemon=True).start()

    @staticmethod
    def _requests(
        client: socket.socket, upstream: socket.socket, turn: threading.Semaphore
    ) -> None:
        """Pass the requests on one frame at a time, each after the previous answer (the
        simulator's server reads one frame per packet: two requests in one were lost)."""
        try:
            while True:
                header = _exactly(client, 7)
                length = struct.unpack(">H", header[4:6])[0]
                frame = header + _exactly(client, length - 1)
                turn.acquire(timeout=1.0)
                upstream.sendall(frame)
        except OSError:
            pass
        finally:
            upstream.close()
            client.close()

    def _answers(
        self, client: socket.socket, upstream: socket.socket, turn: threading.Semaphore
    ) -> None:
        try:
            while True:
                header = _exactly(upstream, 7)
                length = struct.unpack(">H", header[4:6])[0]
                body = bytearray(_exactly(upstream, length - 1))
                if self.broken.is_set() and header[6] == self.device_id:
                    self._break(body)
                client.sendall(header + bytes(body))
                turn.release()
        except OSError:
            pass
        finally:
            client.close()
            upstream.close()

    def _break(self, body: bytearray) -> None:
        if len(body) == 2 + 32 and body[0] == 4 and body[1] == 32:  # FC4, 16 registers
            value = 2 + 2 * self.channel
            status = 2 + 2 * (8 + self.channel)
            body[value : value + 2] = struct.pack(">H", 32767)
            body[status : status + 2] = struct.pack(">H", 1)

    def close(self) -> None:
        self._listener.close()


def _exactly(sock: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = sock.recv(n - len(data))
        if not chunk:
            raise OSError("closed")
        data += chunk
    return data
