"""TD3 recipes for the BRSL safety layer and the paper's baselines, by concern:

``setup`` (config, seeds, threads), ``tasks`` (a task's bare env and offline data), ``safety_models``
(BRSL's reachability models and layer), ``baselines``, ``environments`` (the training env), ``networks``
(actor, critic, exploration, planner), ``runs`` (finished runs on disk); entry points ``train``, ``evaluate``,
``compare``, ``table``, ``demo`` and ``reach_demo``.
"""
import warnings

warnings.filterwarnings("ignore", category=DeprecationWarning, module="torchrl")
