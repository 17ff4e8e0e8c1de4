"""The viewer layout (a Rerun blueprint) written in code."""

from __future__ import annotations

from collections.abc import Collection, Sequence

import rerun.blueprint as rrb

from lcdata.viewer.streams import STEP, VIEWS, path

SHOWN_LEVELS = ["INFO", "WARN", "ERROR", "CRITICAL"]
"""Text-log levels shown at first (keep-lane decisions and lane invasions are DEBUG: one click away)."""
FOLLOW_X_M = (-45.0, 75.0)
"""Road shown behind / ahead of the ego in the scene view (m)."""
FOLLOW_Y_M = (-16.0, 16.0)
"""Road shown right / left of the ego in the scene view (m, screen y points to the right of the road)."""


_PLOTS = (("speed", "speed (km/h)"), ("reward", "reward per decision"), ("return", "return"),
          ("lane", "lane / target lane / action"), ("planner", "planner: share of imagined futures survived"))
"""The time-series views: (view in :data:`~lcdata.viewer.streams.VIEWS`, title), entity ``plots/<view>``."""


def _stack(views: list[rrb.Container | rrb.View], shares: list[float]) -> rrb.Container | rrb.View | None:
    """The views one above the other (``shares`` of the height for two), the view alone, or None."""
    if len(views) > 1:
        return rrb.Vertical(*views, row_shares=shares)
    return views[0] if views else None


def _follow_view(prefix: str, name: str) -> rrb.Spatial2DView:
    return rrb.Spatial2DView(
        name=name,
        origin=path(prefix, "world/ego"),
        contents=f"/{path(prefix, 'world')}/**",
        visual_bounds=rrb.VisualBounds2D(x_range=FOLLOW_X_M, y_range=FOLLOW_Y_M),
        background=(40, 40, 46),
    )


def episode_views(prefix: str, title: str = "", shown: Collection[str] = VIEWS) -> rrb.Container:
    """Views of one episode: scene (following the ego) and overview, image, plots and text logs; only
    those in ``shown`` (:func:`~lcdata.viewer.streams.views_with_data`), the others leave no empty panel."""
    name = f"{title}: " if title else ""
    left: list[rrb.Container | rrb.View] = []
    right: list[rrb.Container | rrb.View] = []
    if "world" in shown:
        overview = rrb.Spatial2DView(
            name=f"{name}whole road", origin=path(prefix, "world"), background=(40, 40, 46)
        )
        left.append(rrb.Tabs(_follow_view(prefix, f"{name}scene (follows the ego)"), overview))
    plots = [rrb.TimeSeriesView(name=label, origin=path(prefix, f"plots/{view}"))
             for view, label in _PLOTS if view in shown]  # fmt: skip
    if plots:
        left.append(rrb.Grid(*plots, grid_columns=min(2, len(plots))))
    if "camera" in shown:
        right.append(rrb.Spatial2DView(name=f"{name}bird's-eye semantic", origin=path(prefix, "camera")))
    if "log" in shown:
        right.append(rrb.TextLogView(
            name=f"{name}events and decisions",
            origin=path(prefix, "log"),
            rows=rrb.TextLogRows(filter_by_log_level=SHOWN_LEVELS),
        ))  # fmt: skip
    columns = [c for c in (_stack(left, [3, 2]), _stack(right, [1, 1])) if c is not None]
    return rrb.Horizontal(*columns, column_shares=[3, 1] if len(columns) == 2 else None)


def blueprint(prefixes: Sequence[str], titles: Sequence[str] = (),
              shown: Sequence[Collection[str]] = ()) -> rrb.Blueprint:  # fmt: skip
    """One episode (a single prefix) fills the window; several are laid out side by side as tabs
    of full layouts plus one column of scenes next to each other.

    ``shown``: per episode, the views that have data (default: all of :data:`~lcdata.viewer.streams.VIEWS`).
    """
    titles = list(titles) or [""] * len(prefixes)
    shown = list(shown) or [VIEWS] * len(prefixes)
    if len(prefixes) == 1:
        body: rrb.Container = episode_views(prefixes[0], shown=shown[0])
    else:
        episodes = list(zip(prefixes, titles, shown, strict=True))
        scenes = [_follow_view(p, f"{title}: scene") for p, title, views in episodes if "world" in views]
        returns = [f"/{path(p, 'plots/return')}" for p, _, views in episodes if "return" in views]
        speeds = [f"/{path(p, 'plots/speed/ego')}" for p, _, views in episodes if "speed" in views]
        plots = [rrb.TimeSeriesView(name=name, contents=contents)
                 for name, contents in (("return", returns), ("ego speed (km/h)", speeds)) if contents]  # fmt: skip
        columns = [c for c in (_stack(scenes, [1] * len(scenes)), _stack(plots, [1, 1])) if c is not None]
        side = rrb.Horizontal(
            *columns, column_shares=[3, 1] if len(columns) == 2 else None, name="side by side"
        )
        body = rrb.Tabs(side, *(episode_views(p, t, views) for p, t, views in episodes))
    return rrb.Blueprint(
        body,
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=STEP),
    )
