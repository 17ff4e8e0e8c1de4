"""Planning: drivers that imagine futures in copies of the simulator, and what they imagine in.

- :mod:`lcsim.planning.perception`: :func:`imagined_copy`, :func:`redraw_future`, :func:`perceive`,
  :func:`estimated_desired_speeds` (what a planner may know).
- :mod:`lcsim.planning.safety`: :class:`SafetyLayerConfig` (how the safety layer imagines; the one config of
  recipes, commands, zoo cards and training behind the layer) and the driver specs that name the layer.
- :mod:`lcsim.planning.lookahead`: :class:`LookaheadDriver` (the safety layer: a driver's decision checked
  against the imagined futures) and :func:`rule_behind_layer` (the rule-based driver behind it).
- :mod:`lcsim.planning.report`: :class:`DecisionReport` (what a decider scored for each candidate at its last
  decision) and :class:`ImaginedPaths` (the ego's paths in the futures it imagined, kept when asked).
- :mod:`lcsim.planning.oracle`: :class:`OracleDriver` (a whole-episode search; the ceiling for any policy).

The physics (:mod:`lcsim.sim`) knows nothing of planners.
"""

from lcsim.planning.lookahead import LookaheadDriver, rule_behind_layer
from lcsim.planning.oracle import OracleDriver, SearchResult, replay, search_episode, search_from
from lcsim.planning.perception import estimated_desired_speeds, imagined_copy, perceive, redraw_future
from lcsim.planning.report import MAX_IMAGINED_FUTURES, DecisionReport, ImaginedPaths
from lcsim.planning.safety import PRIVILEGED, SafetyLayerConfig

__all__ = [
    "MAX_IMAGINED_FUTURES",
    "PRIVILEGED",
    "DecisionReport",
    "ImaginedPaths",
    "LookaheadDriver",
    "OracleDriver",
    "SafetyLayerConfig",
    "SearchResult",
    "estimated_desired_speeds",
    "imagined_copy",
    "perceive",
    "redraw_future",
    "replay",
    "rule_behind_layer",
    "search_episode",
    "search_from",
]
