"""The README's obstacle snippet runs and gives the layer's obstacles entry."""
import re
from pathlib import Path

import torch
from tensordict import TensorDict

README = Path(__file__).resolve().parents[2] / "README.md"


def test_readme_obstacle_snippet_builds_the_obstacles_entry():
    blocks = [b for b in re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S) if "obstacle_batch(" in b]
    assert len(blocks) == 1
    namespace = {"td": TensorDict()}
    exec(blocks[0], namespace)
    obstacles = namespace["td"]["obstacles"]
    assert obstacles["center"].shape == (8, 2) and obstacles["generators"].shape == (8, 2, 6)
    assert obstacles["mask"].tolist() == [True] * 4 + [False] * 4
    assert obstacles["center"].dtype == torch.float64 and obstacles["mask"].dtype == torch.bool
