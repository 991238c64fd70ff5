"""The safety layer: plan verification, adjustment, failsafe, the step's decision and the TorchRL transform."""
from torchrl_brsl.safety.adjust import Adjustment, FacetQPAdjuster, GradientAdjuster
from torchrl_brsl.safety.decision import INPUT_LIMIT, SafetyDecision, StepDecision
from torchrl_brsl.safety.failsafe import Failsafe
from torchrl_brsl.safety.layer import ADJUSTERS, DIAGNOSTICS, BRSLSafetyLayer
from torchrl_brsl.safety.plan_check import COLLISION_CHECKS, DEFAULT_STOP_SLACK, Gauge, PlanChecker, PlanEvaluation

__all__ = ["ADJUSTERS", "COLLISION_CHECKS", "DEFAULT_STOP_SLACK", "DIAGNOSTICS", "INPUT_LIMIT", "Adjustment",
           "BRSLSafetyLayer", "FacetQPAdjuster", "Failsafe", "Gauge", "GradientAdjuster", "PlanChecker", "PlanEvaluation",
           "SafetyDecision", "StepDecision"]
