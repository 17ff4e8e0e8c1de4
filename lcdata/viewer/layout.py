"""The viewer layout (a Rerun blueprint) written in code."""

from __future__ import annotations

from collections.abc import Sequence

import rerun.blueprint as rrb

from lcdata.viewer.streams import STEP, path

SHOWN_LEVELS = ["INFO", "WARN", "ERROR", "CRITICAL"]
"""Text-log levels shown at first (keep-lane decisions and lane invasions are DEBUG: one click away)."""
FOLLOW_X_M = (-45.0, 75.0)
"""Road shown behind / ahead of the ego in the scene view (m)."""
FOLLOW_Y_M = (-16.0, 16.0)
"""Road shown right / left of the ego in the scene view (m, screen y points to the right of the road)."""


def episode_views(prefix: str, title: str = "") -> rrb.Container:
    """Views of one episode: scene (following the ego) and overview, image, plots and text logs."""
    name = f"{title}: " if title else ""
    follow = rrb.Spatial2DView(
        name=f"{name}scene (follows the ego)",
        origin=path(prefix, "world/ego"),
        contents=f"/{path(prefix, 'world')}/**",
        visual_bounds=rrb.VisualBounds2D(x_range=FOLLOW_X_M, y_range=FOLLOW_Y_M),
        background=(40, 40, 46),
    )
    overview = rrb.Spatial2DView(
        name=f"{name}whole road", origin=path(prefix, "world"), background=(40, 40, 46)
    )
    camera = rrb.Spatial2DView(name=f"{name}bird's-eye semantic", origin=path(prefix, "camera"))
    plots = rrb.Grid(
        rrb.TimeSeriesView(name="speed (km/h)", origin=path(prefix, "plots/speed")),
        rrb.TimeSeriesView(name="reward per decision", origin=path(prefix, "plots/reward")),
        rrb.TimeSeriesView(name="return", origin=path(prefix, "plots/return")),
        rrb.TimeSeriesView(name="lane / target lane / action", origin=path(prefix, "plots/lane")),
        grid_columns=2,
    )
    logs = rrb.TextLogView(
        name=f"{name}events and decisions",
        origin=path(prefix, "log"),
        rows=rrb.TextLogRows(filter_by_log_level=SHOWN_LEVELS),
    )
    return rrb.Horizontal(
        rrb.Vertical(rrb.Tabs(follow, overview), plots, row_shares=[3, 2]),
        rrb.Vertical(camera, logs, row_shares=[1, 1]),
        column_shares=[3, 1],
    )


def blueprint(prefixes: Sequence[str], titles: Sequence[str] = ()) -> rrb.Blueprint:
    """One episode (a single prefix) fills the window; several are laid out side by side as tabs
    of full layouts plus one column of scenes next to each other."""
    titles = list(titles) or [""] * len(prefixes)
    if len(prefixes) == 1:
        body: rrb.Container = episode_views(prefixes[0])
    else:
        scenes = rrb.Vertical(*(
            rrb.Spatial2DView(
                name=f"{title}: scene", origin=path(p, "world/ego"), contents=f"/{path(p, 'world')}/**",
                visual_bounds=rrb.VisualBounds2D(x_range=FOLLOW_X_M, y_range=FOLLOW_Y_M), background=(40, 40, 46),
            )
            for p, title in zip(prefixes, titles, strict=True)
        ))  # fmt: skip
        returns = rrb.TimeSeriesView(
            name="return", contents=[f"/{path(p, 'plots/return')}" for p in prefixes]
        )
        speeds = rrb.TimeSeriesView(
            name="ego speed (km/h)", contents=[f"/{path(p, 'plots/speed/ego')}" for p in prefixes]
        )
        side = rrb.Horizontal(
            scenes, rrb.Vertical(returns, speeds), column_shares=[3, 1], name="side by side"
        )
        body = rrb.Tabs(side, *(episode_views(p, t) for p, t in zip(prefixes, titles, strict=True)))
    return rrb.Blueprint(
        body,
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=STEP),
    )
