"""Road geometry behind a small interface, so curved roads or an OpenDRIVE import can come later.

The simulator works in road coordinates (``s`` along the road, ``d`` to the left of the right edge).
On :class:`StraightRoad` these equal the world coordinates ``x`` and ``y``.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from lcsim.config import RoadConfig

SOLID, BROKEN = 0, 1


class Road(Protocol):
    config: RoadConfig

    def lane_center(self, lane: np.ndarray | int) -> np.ndarray | float: ...
    def lane_of(self, d: np.ndarray) -> np.ndarray: ...
    def on_road(self, d: np.ndarray) -> np.ndarray: ...
    def markings(self) -> list[tuple[float, int]]: ...


class StraightRoad:
    """A straight carriageway along +x: lanes 0..L-1 from right to left, solid edges, broken lines between.

    Marking ``k`` (0..L) is the line at ``y = k * lane_width_m``; 0 and L are the solid edges.
    """

    def __init__(self, config: RoadConfig) -> None:
        self.config = config
        self.lane_width = config.lane_width_m
        self.num_lanes = config.num_lanes
        self.width = config.width_m

    def lane_center(self, lane: np.ndarray | int) -> np.ndarray | float:
        """Lateral position of a lane's centre line (m); accepts -1 and L for the shoulders."""
        return (np.asarray(lane) + 0.5) * self.lane_width

    def lane_of(self, d: np.ndarray) -> np.ndarray:
        """Index of the lane containing lateral position ``d``, clipped to [0, L-1]. Shape as ``d``."""
        return np.clip(np.floor(np.asarray(d) / self.lane_width), 0, self.num_lanes - 1).astype(np.int64)

    def on_road(self, d: np.ndarray) -> np.ndarray:
        """Whether a point is between the two solid edge lines."""
        d = np.asarray(d)
        return (d >= 0.0) & (d <= self.width)

    def markings(self) -> list[tuple[float, int]]:
        """``(y, kind)`` of every marking, right to left; kind is SOLID or BROKEN."""
        return [(k * self.lane_width, SOLID if k in (0, self.num_lanes) else BROKEN)
                for k in range(self.num_lanes + 1)]
