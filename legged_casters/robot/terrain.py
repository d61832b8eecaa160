"""Planar slopes on the floor: a course of straight segments along +x.

Each segment is (length m, slope deg) and starts where the previous one ended, at its
height; the course starts at x = `start_x` on the floor (z = 0) and runs across y in
[-width / 2, width / 2]. Every segment is one box whose top face is the ground there;
the boxes reach down into the floor, so there is no gap under a kink. A course must
stay at or above z = 0 (the floor plane is still there): climb before descending.
The boxes collide with the robot exactly as the floor does (same contact settings).
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
import torch

from legged_casters.robot.caster import ContactParams, set_contact


def profile(segments, start_x: float = 0.0) -> list[tuple[float, float, float, float]]:
    """(x0, z0, x1, z1) of each segment's top edge."""
    out, x, z = [], start_x, 0.0
    for length, slope_deg in segments:
        if length <= 0:
            raise ValueError(f"terrain segment length must be positive, got {length}")
        a = math.radians(slope_deg)
        x1, z1 = x + length * math.cos(a), z + length * math.sin(a)
        out.append((x, z, x1, z1))
        x, z = x1, z1
    if min(min(p[1], p[3]) for p in out) < -1e-9:
        raise ValueError("the terrain goes below the floor (z < 0): climb before descending")
    return out


class Course:
    """A course's ground height, built once: `height(x)` (numpy, floats or arrays) and
    `height_torch(x)` (a tensor of x, for the env's every step). 0 off the course."""

    def __init__(self, segments, start_x: float = 0.0):
        edges = profile(segments, start_x) if segments else [(start_x, 0.0, start_x, 0.0)]
        self.xs = np.array([edges[0][0]] + [e[2] for e in edges])
        self.zs = np.array([edges[0][1]] + [e[3] for e in edges])
        self._torch: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}

    @property
    def end(self) -> float:
        """x where the course ends."""
        return float(self.xs[-1])

    def height(self, x):
        return np.interp(x, self.xs, self.zs, left=0.0, right=0.0)

    def height_torch(self, x: torch.Tensor) -> torch.Tensor:
        key = (x.dtype, x.device)
        if key not in self._torch:
            self._torch[key] = (torch.as_tensor(self.xs, dtype=x.dtype, device=x.device),
                                torch.as_tensor(self.zs, dtype=x.dtype, device=x.device))  # fmt: skip
        xs, zs = self._torch[key]
        i = torch.searchsorted(xs, x.contiguous()).clamp(1, len(xs) - 1)
        x0, x1, z0, z1 = xs[i - 1], xs[i], zs[i - 1], zs[i]
        z = z0 + (z1 - z0) * (x - x0) / (x1 - x0).clamp(min=1e-9)
        return torch.where((x >= xs[0]) & (x <= xs[-1]), z, torch.zeros_like(x))


def add_course(spec: mujoco.MjSpec, segments, start_x: float = 0.0, width: float = 4.0) -> None:
    """Add the course's boxes to the world body of `spec`."""
    contact = ContactParams()
    for i, (x0, z0, x1, z1) in enumerate(profile(segments, start_x)):
        length = math.hypot(x1 - x0, z1 - z0)
        angle = math.atan2(z1 - z0, x1 - x0)
        depth = max(z0, z1) + 0.5  # reaches into the floor
        # Box frame: x along the top edge, z its normal; the centre lies depth/2 below the top face.
        nx, nz = -math.sin(angle), math.cos(angle)
        cx, cz = (x0 + x1) / 2 - nx * depth / 2, (z0 + z1) / 2 - nz * depth / 2
        geom = spec.worldbody.add_geom(
            name=f"terrain_{i}",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[length / 2, width / 2, depth / 2],
            pos=[cx, 0.0, cz],
            quat=[math.cos(-angle / 2), 0.0, math.sin(-angle / 2), 0.0],
        )
        geom.rgba = [0.45, 0.5, 0.45, 1.0]
        set_contact(geom, contact, robot=False)
