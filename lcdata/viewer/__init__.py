"""Recorded episodes (MCAP) -> Rerun: entities, time lines and the layout used by ``lc-view``.

``log_episode(rec, episode)`` logs one :class:`~lcdata.reader.Episode` with columnar calls
(:func:`rerun.send_columns`), one function per data stream (:mod:`lcdata.viewer.streams`):

=============================  ==============================================================
entity                         content
=============================  ==============================================================
``world/road/*``               lane edges, broken markings, shoulders, lane centres (static; none without a road in the config)
``world/vehicles/boxes``       every traffic vehicle as an oriented box (closed line strip)
``world/vehicles/trails``      the last 2 s of every vehicle, the ego's included
``world/ego``                  the ego frame (translation per step), followed by the scene view
``world/ego/box``              the ego's box, highlighted
``world/prediction/*``         predicted vs. actual trajectories of the nearest vehicles
``world/planner/imagined``     the ego's paths in the futures a planning driver imagined, by candidate (``/planner/decision``)
``world/planner/crashes``      where the imagined futures the ego did not survive ended
``camera/bev``                 bird's-eye semantic image (SegmentationImage, named classes)
``plots/speed|reward|return|lane``  time series
``plots/planner/right|keep|left``  each candidate's score at each decision where a planning driver had a choice
``plots/planner/overridden``   the executed candidate's score where the planner overrode the proposal
``log/events``, ``log/decisions``, ``log/planner``   text logs
=============================  ==============================================================

Time lines: ``step`` (simulation step) and ``sim_time`` (simulation time). The scene is drawn
top-down with x to the right and the road's left (+y) upwards (see :mod:`lcdata.viewer.geometry`).
The layout (:func:`blueprint`) has a view only for what the file holds (:func:`views_with_data`): a corpus
recording, without bird's-eye images, gets no image view.
"""

from __future__ import annotations

import rerun as rr

from lcdata.reader import Episode
from lcdata.viewer import streams
from lcdata.viewer.geometry import TrackGrid
from lcdata.viewer.layout import blueprint, episode_views
from lcdata.viewer.streams import SIM_TIME, STEP, VIEWS, describe, views_with_data

__all__ = ["SIM_TIME", "STEP", "VIEWS", "blueprint", "describe", "episode_views", "log_episode", "views_with_data"]


def log_episode(rec: rr.RecordingStream, episode: Episode, prefix: str = "", index: int = 0) -> None:
    """Log every stream of ``episode`` to ``rec`` under the entity prefix ``prefix``.

    ``index``: the episode's place among episodes side by side (a prefix given), which picks the colour of
    its return and ego speed (:data:`~lcdata.viewer.streams.EPISODE_RGB`) in the plots they share.
    """
    rgb = streams.EPISODE_RGB[index % len(streams.EPISODE_RGB)] if prefix else None
    grid, tracks = TrackGrid.from_tracks(episode.tracks)
    streams.log_road(rec, episode, prefix, streams.road_x_range(tracks))
    streams.log_vehicles(rec, episode, prefix, grid, tracks)
    streams.log_ego(rec, episode, prefix, grid, tracks)
    streams.log_predictions(rec, episode, prefix, grid)
    streams.log_planner(rec, episode, prefix)
    streams.log_camera(rec, episode, prefix)
    streams.log_speed(rec, episode, prefix, grid, tracks, rgb)
    streams.log_rewards(rec, episode, prefix, rgb)
    streams.log_lanes(rec, episode, prefix, tracks)
    streams.log_events(rec, episode, prefix)
