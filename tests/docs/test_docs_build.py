"""The documentation site builds: Sphinx, warnings as errors, every tutorial executed.

Marked ``docs`` (``make test`` leaves it out, ``make docs`` runs it) and skipped where Sphinx is
not installed (``pip install -e '.[docs]'``). The site lands in ``docs/_build/html``.
"""
import os
import subprocess
import sys
from pathlib import Path

import pytest

DOCS = Path(__file__).resolve().parents[2] / "docs"
HTML = DOCS / "_build" / "html"
PAGES = ["index", "install", "quickstart", "method", "local_model", "own_robot", "recipes", "results",
         "baselines", "limits", "tasks/index", "tasks/diffdrive_nav", "api/index", "api/safety", "api/envs",
         "auto_tutorials/index", "auto_tutorials/plot_1_layer_on_a_task", "auto_tutorials/plot_2_adjustment",
         "auto_tutorials/plot_3_fit_your_data"]


def build_command() -> list[str]:
    """``sphinx-build`` with warnings as errors, all of them reported before failing."""
    return [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-b", "html", "-q", str(DOCS), str(HTML)]


@pytest.mark.docs
def test_the_site_builds_without_warnings():
    pytest.importorskip("sphinx")
    pytest.importorskip("sphinx_gallery")
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"), OMP_NUM_THREADS="1", MPLBACKEND="Agg")
    result = subprocess.run(build_command(), cwd=DOCS.parent, env=env, capture_output=True, text=True)
    assert result.returncode == 0, f"sphinx-build failed:\n{result.stdout[-5000:]}\n{result.stderr[-10000:]}"
    for page in PAGES:
        assert (HTML / f"{page}.html").exists(), f"{page}.html was not built"
    safety = (HTML / "api" / "safety.html").read_text()
    assert 'id="torchrl_brsl.safety.BRSLSafetyLayer"' in safety  # autodoc filled the API page
    tutorial = (HTML / "auto_tutorials" / "plot_1_layer_on_a_task.html").read_text()
    assert "sphx-glr-single-img" in tutorial or "sphx-glr-multi-img" in tutorial  # the example ran and plotted
