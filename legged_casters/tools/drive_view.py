"""The viewers of ``play.py --drive``: keys in, the robot and the command out.

Two viewers, one interface (`DriveView`: ``keys()``, ``show(qpos, status)``,
``is_running()``, ``close()``):

* `WebDriveView`: MuJoCo Studio's web viewer, for a machine without a display. It serves
  a page (HTTP and WebSockets on one port, bound to 127.0.0.1 unless asked otherwise);
  the browser renders the scene itself and sends its keyboard and mouse input back over
  the page's /ui WebSocket into a headless ImGui context in this process. A viewer-side
  plugin (`_BrowserKeys`) reads the driving keys from that context each frame
  (``imgui.IsKeyPressed``) and sends them to the simulation side as `KeyEvent`s; the
  drive loop collects them at its next ``ViewerHandle.sync()`` (`_SimKeys`). The same
  plugin draws the status (command, measured speed, keys) as an ImGui window that the
  page overlays on the scene.
* `DesktopDriveView`: MuJoCo's passive desktop viewer with a key_callback.

The viewers carry no authentication: anyone who reaches the port drives the robot.
"""

from __future__ import annotations

import contextlib
import dataclasses
import queue
import socket
import threading
import time

import mujoco
import numpy as np
from mujoco.studio import launch_thread, messages, plugin, viewer_protocol, web_viewer
from mujoco.studio.dear_imgui import dear_imgui as imgui
from mujoco.studio.web import web_server

from legged_casters.deploy import keyboard

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080


# --- MuJoCo Studio's web viewer ----------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class KeyEvent(messages.Event):
    """A driving key pressed in the browser (a name of keyboard.KEYS)."""

    key: str


@dataclasses.dataclass(frozen=True)
class StatusSnapshot(messages.Snapshot):
    """The lines the page shows over the scene."""

    lines: tuple[str, ...]


class _BrowserKeys(plugin.ViewerPlugin):
    """Viewer side: driving keys from the browser's input -> KeyEvents; the status overlay."""

    def __init__(self, track_body: int, distance: float):
        self.lines: tuple[str, ...] = ()
        self.track_body, self.distance = track_body, distance
        self.codes = [(name, getattr(imgui.Key, keyboard.imgui_key_attr(name))) for name in keyboard.KEYS]

    @messages.handler
    def on_init(self, event: viewer_protocol.ViewerInitEvent) -> None:
        cam = self.viewer.camera
        cam.type = mujoco.mjtCamera.mjCAMERA_TRACKING
        cam.trackbodyid = self.track_body
        cam.distance = self.distance
        cam.elevation = -20.0
        cam.azimuth = 135.0

    @messages.handler
    def on_status(self, event: StatusSnapshot) -> None:
        self.lines = event.lines

    @messages.handler
    def on_update(self, event: messages.UpdateEvent) -> None:
        if imgui.GetIO().WantCaptureKeyboard:  # typing into a widget
            return
        for name, code in self.codes:
            if imgui.IsKeyPressed(code, False):
                self.viewer.send_to_sim(KeyEvent(name))

    @messages.handler
    def on_gui(self, event: messages.BuildGuiEvent) -> None:
        imgui.SetNextWindowPos(imgui.Vec2(10, 10))
        imgui.SetNextWindowBgAlpha(0.6)
        flags = 0
        for name in ("NoDecoration", "AlwaysAutoResize", "NoFocusOnAppearing", "NoNav"):
            flags |= int(getattr(imgui.WindowFlags, name))
        imgui.Begin("drive", None, flags)
        for line in self.lines:
            imgui.Text(line)
        imgui.End()


class _SimKeys(plugin.SimPlugin):
    """Sim side: KeyEvents arrive here during ViewerHandle.sync(), on the drive loop's thread."""

    def __init__(self):
        self.keys: list[str] = []

    @messages.handler
    def on_key(self, event: KeyEvent) -> None:
        self.keys.append(event.key)


@contextlib.contextmanager
def _bound_to(host: str, sockets: list[socket.socket]):
    """Studio's web viewer binds every interface ('::'); bind `host` instead while it starts
    (and leave its banner out: play.py prints the address it really serves). The bound
    socket is appended to `sockets`."""
    bind, banner = web_server.bind_public_socket, web_viewer._print_url_banner

    def bind_host(_host: str, port: int = 0) -> socket.socket:
        sockets.append(bind(host, port))
        return sockets[-1]

    web_viewer.web_server.bind_public_socket = bind_host
    web_viewer._print_url_banner = lambda *a, **k: None
    try:
        yield
    finally:
        web_viewer.web_server.bind_public_socket, web_viewer._print_url_banner = bind, banner


LISTEN_TIMEOUT = 30.0
"""Seconds the web viewer's server thread gets to start listening on its bound socket."""


def _wait_listening(sockets: list[socket.socket], timeout: float) -> bool:
    """True once the viewer's bound socket listens (SO_ACCEPTCONN), False after `timeout` s."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        with contextlib.suppress(OSError):
            if sockets and sockets[-1].getsockopt(socket.SOL_SOCKET, socket.SO_ACCEPTCONN):
                return True
        time.sleep(0.01)
    return False


class WebDriveView:
    """The scene and the status in a browser; the browser's driving keys back."""

    def __init__(self, model: mujoco.MjModel, track_body: int, host: str = DEFAULT_HOST, port: int = DEFAULT_PORT):
        self.model, self.data = model, mujoco.MjData(model)
        self._sim_keys = _SimKeys()
        ready: queue.Queue = queue.Queue()
        sockets: list[socket.socket] = []
        config = viewer_protocol.ViewerConfig(gfx="web", http_port=port, title="legged_casters drive")

        def target(endpoint) -> None:
            try:
                with _bound_to(host, sockets):
                    viewer = web_viewer.WebViewer(config, endpoint, plugins=[_BrowserKeys(track_body, 2.0)])
            except BaseException as err:
                ready.put(err)
                raise
            ready.put(viewer.port)
            viewer_protocol.run_viewer_loop(viewer)

        self.handle = launch_thread.launch_thread(target, sim_plugins=[self._sim_keys])
        got = ready.get(timeout=60)
        if isinstance(got, BaseException):
            with contextlib.suppress(BaseException):
                self.handle.close()
            raise RuntimeError(f"the web viewer could not start on {host}:{port}: {got}") from got
        # the viewer binds its socket at once but listens from its server thread: the address
        # is only given out once the page can be opened
        if not _wait_listening(sockets, LISTEN_TIMEOUT):
            with contextlib.suppress(BaseException):
                self.handle.close()
            raise RuntimeError(f"the web viewer bound {host}:{got} but did not listen within {LISTEN_TIMEOUT:.0f} s")
        self.host, self.port = host, got
        mujoco.mj_forward(model, self.data)
        self.handle.set_model(model, data=self.data)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    def keys(self) -> list[str]:
        out, self._sim_keys.keys = self._sim_keys.keys, []
        return out

    def show(self, qpos: np.ndarray, lines: tuple[str, ...]) -> None:
        self.data.qpos[:] = qpos
        mujoco.mj_forward(self.model, self.data)
        self.handle.send_to_viewer(StatusSnapshot(tuple(lines)))
        self.handle.sync()  # also collects the keys that came in

    def is_running(self) -> bool:
        return self.handle.is_running()

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self.handle.close()


# --- MuJoCo's desktop viewer ----------------------------------------------------------------------
class DesktopDriveView:
    """MuJoCo's passive viewer (needs a display); keys through its key_callback, the status
    in its text overlay."""

    def __init__(self, model: mujoco.MjModel, track_body: int):
        import mujoco.viewer

        self.model, self.data = model, mujoco.MjData(model)
        self._keys: list[str] = []
        self._lock = threading.Lock()
        self.viewer = mujoco.viewer.launch_passive(model, self.data, key_callback=self._on_key)
        self.viewer.cam.type = mujoco.mjtCamera.mjCAMERA_TRACKING
        self.viewer.cam.trackbodyid = track_body
        self.viewer.cam.distance = 2.0

    def _on_key(self, code: int) -> None:
        name = keyboard.glfw_key_name(code)
        if name is not None:
            with self._lock:
                self._keys.append(name)

    def keys(self) -> list[str]:
        with self._lock:
            out, self._keys = self._keys, []
        return out

    def show(self, qpos: np.ndarray, lines: tuple[str, ...]) -> None:
        with self.viewer.lock():
            self.data.qpos[:] = qpos
            mujoco.mj_forward(self.model, self.data)
        if lines:  # set_texts takes the viewer's lock itself: outside the block above
            font, grid = mujoco.mjtFontScale.mjFONTSCALE_150, mujoco.mjtGridPos.mjGRID_TOPLEFT
            self.viewer.set_texts((font, grid, "\n".join(lines), ""))
        self.viewer.sync()

    def is_running(self) -> bool:
        return self.viewer.is_running()

    def close(self) -> None:
        self.viewer.close()
