"""Offscreen MuJoCo rendering for play.py: EGL or OSMesa, a camera that follows the robot.

The env simulates a texture-less copy of the robot model; frames are drawn from the
full MJCF (floor and sky textures) with the env's joint positions copied in.
"""

from __future__ import annotations

import importlib
import os
import subprocess
import sys

import mujoco
import numpy as np

GL_BACKENDS = ("egl", "osmesa")
INSTALL_HINT = (
    "offscreen rendering needs EGL or OSMesa and neither works here. On Debian/Ubuntu install one of them: "
    "`apt-get install libegl1 libegl-mesa0` (EGL; GPU driver or Mesa) or `apt-get install libosmesa6` "
    "(OSMesa, software), then retry; or pass --no_video to write only the plots"
)


def probe_gl_backend() -> tuple[str | None, dict[str, str]]:
    """The first of EGL / OSMesa that can create a context here (each tried in a child
    process, so a failure cannot leave this one half-initialised), and why the others failed."""
    fixed = os.environ.get("PYOPENGL_PLATFORM", "").lower()
    wanted = os.environ.get("MUJOCO_GL", "").lower()
    order = [fixed] if fixed in GL_BACKENDS else [b for b in (wanted, *GL_BACKENDS) if b in GL_BACKENDS]
    order = list(dict.fromkeys(order))
    errors = {}
    for backend in order:
        code = f"from mujoco.{backend} import GLContext\nc = GLContext(64, 64)\nc.make_current()\nc.free()\n"
        env = {**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend}
        try:
            out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
        except (OSError, subprocess.TimeoutExpired) as err:
            errors[backend] = str(err)
            continue
        if out.returncode == 0:
            return backend, errors
        lines = (out.stderr or out.stdout).strip().splitlines()
        errors[backend] = lines[-1] if lines else f"exit code {out.returncode}"
    return None, errors


class FollowRenderer:
    """Draws `num_robots` copies of a robot model; the camera tracks robot 0's trunk."""

    def __init__(
        self,
        model_path: str,
        gl_backend: str,
        width: int = 640,
        height: int = 480,
        num_robots: int = 1,
        spacing: float = 1.0,
        track_body: str = "trunk",
        fast: bool = False,
    ):
        os.environ.setdefault("PYOPENGL_PLATFORM", gl_backend)
        self.model = mujoco.MjModel.from_xml_path(str(model_path))
        self.model.vis.global_.offwidth = max(self.model.vis.global_.offwidth, width)
        self.model.vis.global_.offheight = max(self.model.vis.global_.offheight, height)
        self.datas = [mujoco.MjData(self.model) for _ in range(num_robots)]
        self.width, self.height, self.spacing = width, height, spacing
        gl = importlib.import_module(f"mujoco.{gl_backend}")
        self.gl = gl.GLContext(width, height)
        self.gl.make_current()
        self.scene = mujoco.MjvScene(self.model, maxgeom=1000 * num_robots)
        self.context = mujoco.MjrContext(self.model, mujoco.mjtFontScale.mjFONTSCALE_150)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self.context)
        if fast:  # software GL (llvmpipe) spends most of a frame on these
            self.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
            self.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
        self.viewport = mujoco.MjrRect(0, 0, width, height)
        self.option, self.perturb = mujoco.MjvOption(), mujoco.MjvPerturb()
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_TRACKING
        self.camera.trackbodyid = self.model.body(track_body).id
        self.camera.distance, self.camera.azimuth, self.camera.elevation = 1.8, 135.0, -20.0
        self.rgb = np.zeros((height, width, 3), dtype=np.uint8)

    def render(self, qpos: np.ndarray, overlay: str = "") -> np.ndarray:
        """An RGB frame (height, width, 3) of robots at qpos (num_robots, nq); robot i is
        drawn shifted by i * spacing along the world y axis."""
        qpos = np.atleast_2d(qpos)
        if qpos.shape[1] != self.model.nq:
            raise ValueError(f"qpos has {qpos.shape[1]} columns, the render model nq {self.model.nq}")
        self.gl.make_current()
        for i, data in enumerate(self.datas[: len(qpos)]):
            data.qpos[:] = qpos[i]
            data.qpos[1] += i * self.spacing
            mujoco.mj_forward(self.model, data)
        mujoco.mjv_updateScene(
            self.model, self.datas[0], self.option, self.perturb, self.camera, mujoco.mjtCatBit.mjCAT_ALL, self.scene
        )
        for data in self.datas[1 : len(qpos)]:
            mujoco.mjv_addGeoms(self.model, data, self.option, self.perturb, mujoco.mjtCatBit.mjCAT_DYNAMIC, self.scene)
        mujoco.mjr_render(self.viewport, self.scene, self.context)
        if overlay:
            mujoco.mjr_overlay(
                mujoco.mjtFont.mjFONT_NORMAL, mujoco.mjtGridPos.mjGRID_TOPLEFT, self.viewport, overlay, "", self.context
            )
        mujoco.mjr_readPixels(self.rgb, None, self.viewport, self.context)
        return np.flipud(self.rgb).copy()

    def close(self) -> None:
        if self.gl is not None:
            self.context.free()
            self.gl.free()
            self.gl = None
