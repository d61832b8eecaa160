"""play.py --drive in a browser, for real: play.py serves MuJoCo Studio's web viewer with no
display, headless Chromium opens the page (driven over the Chrome DevTools protocol), the
page shows the robot (a screenshot), and keys pressed in the page change the command the
policy receives (play.py prints it). Skipped where Chromium is not installed."""

from __future__ import annotations

import base64
import itertools
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from legged_casters.deploy.keyboard import STEPS

REPO = Path(__file__).resolve().parents[1]
CHROMIUM = next((shutil.which(n) for n in ("chromium", "chromium-browser", "google-chrome") if shutil.which(n)), None)
COMMAND = re.compile(r"command\s+vx ([-+]\d+\.\d+)\s+vy ([-+]\d+\.\d+)\s+wz ([-+]\d+\.\d+)\s+(\S.*?) \|")

pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="needs Chromium (apt-get install chromium) for the browser")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _Lines:
    """A process's output lines, read on a thread; wait() for one that matches."""

    def __init__(self, proc: subprocess.Popen):
        self.lines: list[str] = []
        self.cond = threading.Condition()
        threading.Thread(target=self._read, args=(proc,), daemon=True).start()

    def _read(self, proc):
        for line in proc.stdout:
            with self.cond:
                self.lines.append(line.rstrip("\n"))
                self.cond.notify_all()

    def wait(self, pred, timeout: float, start: int = 0) -> tuple[int, str]:
        """(index, line) of the first line from `start` on with pred(line)."""
        end = time.time() + timeout
        with self.cond:
            while True:
                for i in range(start, len(self.lines)):
                    if pred(self.lines[i]):
                        return i, self.lines[i]
                start = len(self.lines)
                left = end - time.time()
                if left <= 0:
                    raise AssertionError(f"no such line in {timeout} s; output:\n" + "\n".join(self.lines[-40:]))
                self.cond.wait(left)


class _Cdp:
    """The least of the Chrome DevTools protocol: call(method, **params) -> result."""

    def __init__(self, ws):
        self.ws, self.ids = ws, itertools.count(1)

    def call(self, method: str, **params):
        i = next(self.ids)
        self.ws.send(json.dumps({"id": i, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv(timeout=30))
            if msg.get("id") == i:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})

    def key(self, key: str, code: str, vk: int) -> None:
        self.call("Input.dispatchKeyEvent", type="keyDown", key=key, code=code, windowsVirtualKeyCode=vk, text=key)
        time.sleep(0.15)
        self.call("Input.dispatchKeyEvent", type="keyUp", key=key, code=code, windowsVirtualKeyCode=vk)
        time.sleep(0.25)

    def screenshot(self, path: Path) -> np.ndarray:
        path.write_bytes(base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"]))
        from PIL import Image

        return np.asarray(Image.open(path).convert("RGB"))


def _listen_addresses(port: int) -> set[str]:
    """Local addresses a socket listens on at `port` (Linux /proc/net/tcp*)."""
    out = set()
    for name in ("tcp", "tcp6"):
        p = Path("/proc/net") / name
        if not p.exists():
            continue
        for row in p.read_text().splitlines()[1:]:
            local, state = row.split()[1], row.split()[3]
            addr, hexport = local.split(":")
            if state == "0A" and int(hexport, 16) == port:  # LISTEN
                raw = bytes.fromhex(addr)
                if len(raw) == 4:
                    out.add(socket.inet_ntop(socket.AF_INET, raw[::-1]))
                else:
                    words = b"".join(raw[k : k + 4][::-1] for k in range(0, 16, 4))
                    out.add(socket.inet_ntop(socket.AF_INET6, words))
    return out


def test_drive_in_a_headless_browser(tmp_path):
    from websockets.sync.client import connect

    port, cdp_port = _free_port(), _free_port()
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    env["PYTHONPATH"] = str(REPO)
    play = subprocess.Popen(
        [sys.executable, "play.py", "--drive", "--port", str(port), "--duration", "120"],
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    out = _Lines(play)
    browser = None
    try:
        url = f"http://127.0.0.1:{port}/"
        _, line = out.wait(lambda s: "command ranges vx [" in s, 90)
        vx_hi = float(re.search(r"vx \[[^,]+, ([^\]]+)\]", line).group(1))
        out.wait(lambda s: f"open {url} in a browser" in s, 60)
        out.wait(lambda s: "ssh -L" in s, 5)
        # the page is served on the loopback interface only
        assert _listen_addresses(port) == {"127.0.0.1"}

        browser = subprocess.Popen(
            [
                CHROMIUM,
                "--headless=new",
                "--no-sandbox",
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
                "--window-size=800,600",
                f"--remote-debugging-port={cdp_port}",
                f"--user-data-dir={tmp_path / 'profile'}",
                "about:blank",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        end = time.time() + 30
        while True:
            try:
                tabs = json.load(urllib.request.urlopen(f"http://127.0.0.1:{cdp_port}/json", timeout=2))
                break
            except OSError:
                if time.time() > end:
                    raise
                time.sleep(0.2)
        page = next(t for t in tabs if t["type"] == "page")
        with connect(page["webSocketDebuggerUrl"], max_size=None) as ws:
            cdp = _Cdp(ws)
            cdp.call("Page.navigate", url=url)
            # the page fetched the model and took control: its keys now reach play.py
            out.wait(lambda s: "UI session" in s and "started" in s, 60)
            time.sleep(4)  # the scene's first frames
            shot = cdp.screenshot(tmp_path / "driving_browser_start.png")
            h, w, _ = shot.shape
            centre = shot[h // 4 : 3 * h // 4, w // 4 : 3 * w // 4].astype(int)
            assert (centre.max(axis=2) < 60).mean() > 0.002, "no dark robot parts in the middle of the page"
            assert (centre.min(axis=2) > 170).mean() > 0.002, "no light robot body in the middle of the page"
            assert shot.std() > 20, "a blank page"

            start = len(out.lines)
            cdp.key("w", "KeyW", 87)
            cdp.key("w", "KeyW", 87)
            _, line = out.wait(lambda s: "(keys w)" in s and COMMAND.search(s), 20, start)
            i, line = out.wait(
                lambda s: (m := COMMAND.search(s)) and float(m.group(1)) > vx_hi / STEPS + 0.01, 20, start
            )
            vx, vy, wz, _ = COMMAND.search(line).groups()
            # two steps of the task's range, as the policy receives it
            assert float(vx) == pytest.approx(2 * vx_hi / STEPS, abs=0.006) and float(vy) == 0 and float(wz) == 0
            time.sleep(1.5)
            cdp.screenshot(tmp_path / "driving_browser.png")  # under way

            cdp.key(" ", "Space", 32)
            i, line = out.wait(lambda s: "(keys space)" in s, 20, i + 1)
            vx, vy, wz, state = COMMAND.search(line).groups()
            assert (float(vx), float(vy), float(wz)) == (0, 0, 0) and state.startswith("STOP")
            cdp.key("w", "KeyW", 87)  # held stopped until R
            _, line = out.wait(lambda s: "(keys w)" in s, 20, i + 1)
            assert COMMAND.search(line).group(1) in ("+0.00", "-0.00")
            cdp.screenshot(tmp_path / "driving_browser_stopped.png")
            cdp.key("r", "KeyR", 82)  # releases the stop and resets the robot; from zero again
            i, line = out.wait(lambda s: "(keys r)" in s, 20, i + 1)
            assert COMMAND.search(line).group(4) == "four_wheel"
            cdp.key("2", "Digit2", 50)
            _, line = out.wait(lambda s: "(keys 2)" in s, 20, i + 1)
            assert COMMAND.search(line).group(4) == "front_wheel"
    finally:
        if browser is not None:
            browser.terminate()
            browser.wait(20)
        play.terminate()
        try:
            play.wait(20)
        except subprocess.TimeoutExpired:
            play.kill()
            play.wait(10)
