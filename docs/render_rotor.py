"""Render ``docs/quadrotor_rotor.png`` and ``docs/hexarotor_rotor.png``: the rotor-driven multirotors
(``robot="rotor"``), close up and tilted as they accelerate.

Usage: ``MUJOCO_GL=egl python docs/render_rotor.py``; prints a note and writes nothing when no OpenGL backend
is available.
"""
import sys

import matplotlib.pyplot as plt
import mujoco
import numpy as np
import torch

import envs

torch.set_num_threads(1)
# task: (image, camera distance, camera azimuth)
FRAMES = {"quadrotor_nav": ("docs/quadrotor_rotor.png", 1.6, 120.0),
          "hexarotor_wind": ("docs/hexarotor_rotor.png", 2.0, 200.0)}

for name, (path, distance, azimuth) in FRAMES.items():
    env = envs.make(name, robot="rotor", seed=0, layout=1)
    td = env.reset()
    for _ in range(3):
        td = env.step_mdp(env.step(td.set("action", torch.tensor([2.5, 1.5, 0.5]))))
    physics = env.physics
    camera = mujoco.MjvCamera()
    camera.lookat[:] = physics.data.qpos[:3]
    camera.distance, camera.azimuth, camera.elevation = distance, azimuth, -25.0
    physics.model.vis.map.znear = 0.002  # the parked obstacles at z = -50 make the extent large
    physics.model.geom_rgba[env.task._robot_geoms[0], 3] = 0.08  # a fainter collision sphere
    try:
        renderer = mujoco.Renderer(physics.model.ptr, 480, 640)
    except Exception as error:  # no OpenGL backend (set MUJOCO_GL=egl or osmesa)
        print(f"rendering unavailable ({error}); {path} not written")
        sys.exit(0)
    renderer.update_scene(physics.data.ptr, camera=camera)
    plt.imsave(path, renderer.render())
    renderer.close()
    tilt = np.degrees(2 * np.arcsin(np.hypot(*physics.data.qpos[4:6])))
    print(f"{path}: {name}, tilted {tilt:.0f} degrees")
