"""Simulation backends: MuJoCo C (`cpu`, mujoco.rollout thread pool) and MuJoCo Warp (`warp`)."""

from legged_casters.sim.base import (
    BACKEND_KINDS,
    RANDOMIZABLE_FIELDS,
    SimBackend,
    make_backend,
    physics_model,
)

__all__ = ["BACKEND_KINDS", "RANDOMIZABLE_FIELDS", "SimBackend", "make_backend", "physics_model"]
