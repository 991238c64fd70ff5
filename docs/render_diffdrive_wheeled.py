"""Render ``docs/diffdrive_wheeled.png``: the wheeled ``diffdrive_nav`` robot, close up.

Usage: ``MUJOCO_GL=egl python docs/render_diffdrive_wheeled.py``.
"""
import matplotlib.pyplot as plt
import mujoco
import numpy as np
import torch

import envs

torch.set_num_threads(1)
env = envs.make("diffdrive_nav", robot="wheeled", seed=0)
td = env.reset()
for _ in range(8):
    td = env.step_mdp(env.step(td.set("action", torch.tensor([0.2, 0.3]))))
physics = env.physics
camera = mujoco.MjvCamera()
camera.lookat[:] = [*physics.data.qpos[:2], 0.1]
camera.distance, camera.azimuth, camera.elevation = 0.7, float(np.degrees(physics.data.qpos[2])) + 150, -20
physics.model.vis.map.znear = 0.002  # the parked obstacles at z = -50 make the extent large
renderer = mujoco.Renderer(physics.model.ptr, 480, 640)
renderer.update_scene(physics.data.ptr, camera=camera)
plt.imsave("docs/diffdrive_wheeled.png", renderer.render())
