"""Planning: drivers that imagine futures in copies of the simulator, and what they imagine in.

- :mod:`lcsim.planning.perception`: :func:`imagined_copy`, :func:`redraw_future`, :func:`perceive`,
  :func:`estimated_desired_speeds` (what a planner may know).
- :mod:`lcsim.planning.lookahead`: :class:`LookaheadDriver` (a driver's decision checked against the
  imagined futures; the safety layer).
- :mod:`lcsim.planning.oracle`: :class:`OracleDriver` (a whole-episode search; the ceiling for any policy).

The physics (:mod:`lcsim.sim`) knows nothing of planners.
"""

from lcsim.planning.lookahead import LookaheadConfig, LookaheadDriver
from lcsim.planning.oracle import OracleDriver, SearchResult, replay, search_episode, search_from
from lcsim.planning.perception import estimated_desired_speeds, imagined_copy, perceive, redraw_future

__all__ = [
    "LookaheadConfig",
    "LookaheadDriver",
    "OracleDriver",
    "SearchResult",
    "estimated_desired_speeds",
    "imagined_copy",
    "perceive",
    "redraw_future",
    "replay",
    "search_episode",
    "search_from",
]
