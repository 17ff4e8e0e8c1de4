"""lc-toolkit models: the trajectory predictor (``lcmodels.predictor``) and, later, the policy.

Submodules are imported on demand so that ``import lcmodels`` stays cheap.
"""

__all__ = ["predictor"]
