"""Estimation stage: real-time inverse problem from cavity volumes to force, pose and targets."""

from softphantom.estimation.types import ARM_NAMES, Estimate

__all__ = ["ARM_NAMES", "Estimate"]
