"""The safety layer: plan verification, adjustment, failsafe and the TorchRL transform."""
from torchrl_brsl.safety.adjust import Adjustment, FacetQPAdjuster, GradientAdjuster
from torchrl_brsl.safety.failsafe import Failsafe
from torchrl_brsl.safety.layer import DIAGNOSTICS, INPUT_LIMIT, BRSLSafetyLayer
from torchrl_brsl.safety.plan_check import DEFAULT_STOP_SLACK, PlanChecker, PlanEvaluation

__all__ = ["DEFAULT_STOP_SLACK", "DIAGNOSTICS", "INPUT_LIMIT", "Adjustment", "BRSLSafetyLayer", "FacetQPAdjuster", "Failsafe", "GradientAdjuster", "PlanChecker",
           "PlanEvaluation"]
