"""Render ``docs/_static/tasks/<task>.png`` for the task pages: a MuJoCo frame beside the top-down map.

Usage: ``MUJOCO_GL=egl python docs/render_tasks.py`` (re-run after changing a task's scene or layouts).
"""
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

import envs  # noqa: E402

OUT = Path(__file__).with_name("_static") / "tasks"


def render(task: str) -> Path:
    torch.manual_seed(0)
    env = envs.make(task, seed=0)
    td = env.reset()
    frame = env.render(360, 480, camera="overview")
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.9), gridspec_kw={"width_ratios": [4, 3]})
    left.imshow(frame)
    left.set_axis_off()
    left.set_title("MuJoCo, overview camera", fontsize=10)
    envs.plot_topdown(td, ax=right, layout=env.layout)
    right.set_title("top-down: true geometry (grey),\ninflated obstacles (red), goals (green)", fontsize=9)
    fig.tight_layout()
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / f"{task}.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


if __name__ == "__main__":
    torch.set_num_threads(1)
    for name in envs.TASKS:
        print(render(name))
