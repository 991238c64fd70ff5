"""MuJoCo / dm_control robot tasks mirroring the experiments of the BRSL paper.

Five tasks, made by name with :func:`make`: ``point_circle`` (2-D double integrator
following a circle), ``diffdrive_nav`` (Turtlebot-like navigation), ``quadrotor_nav``
(3-D navigation), ``hexarotor_wind`` (checkpoints in wind) and ``point_boxes`` (a
velocity-commanded point mass among boxes around its start, where random actions
collide; small and fast, for tests of safety layers). Each is a dm_control
``control.Environment`` wrapped as a TorchRL env whose TensorDict carries
``observation``, ``state``, ``obstacles`` (padded zonotopes ``center``, ``generators``,
``mask``), ``collision``, ``goal_reached`` and ``speed``. :func:`safety_info` describes
what a safety layer needs; :func:`plot_topdown` draws layouts, paths and sets.

``MUJOCO_GL`` defaults to ``egl`` (headless rendering) unless already set.
"""
import os

os.environ.setdefault("MUJOCO_GL", "egl")

from envs._obstacles import Layout, Obstacle  # noqa: E402
from envs._registry import TASKS, make, safety_info  # noqa: E402
from envs._safety_info import SafetyInfo  # noqa: E402
from envs._wrapper import RenderingUnavailable, SafetyTaskEnv  # noqa: E402
from envs.plotting import plot_topdown, zonotope_polygon  # noqa: E402

__all__ = [
    "TASKS",
    "Layout",
    "Obstacle",
    "RenderingUnavailable",
    "SafetyInfo",
    "SafetyTaskEnv",
    "make",
    "plot_topdown",
    "safety_info",
    "zonotope_polygon",
]
