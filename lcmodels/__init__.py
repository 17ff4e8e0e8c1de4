"""lc-toolkit models: the trajectory predictor (``lcmodels.predictor``), the policy (``lcmodels.policy``:
extractor, training wrappers, training, warm start, DAgger, evaluation, policy files), the experiment
pipeline and its report (``lcmodels.experiment``, ``lcmodels.presets``, ``lcmodels.report``) and the
analyses of held-out episodes (``lcmodels.analysis``).

Submodules are imported on demand so that ``import lcmodels`` stays cheap.
"""

__all__ = ["predictor"]
