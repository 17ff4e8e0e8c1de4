"""Figures of a suite table (:func:`lcmodels.bench.table.suite_summary`), written beside BENCH.md as PNG and SVG.

- ``bench_normalised``: per road, one bar per method (its runs' mean normalised score), the ceiling at 1; the error
  bar is the t 95% interval over the method's runs (training seeds) where it has several, else the Wilson 95%
  interval of its success over episodes divided by the ceiling's success.
- ``bench_intervals``: rliable's interval-estimate plot: per method, the interquartile mean and the mean of the
  normalised scores over runs and roads, each with its stratified-bootstrap 95% interval (a point alone where the
  method has one run).

Both are data views of ``bench.json``: what they show is in the table beside them.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from lcmodels.stats import t_interval

FIGURES = ("bench_normalised", "bench_intervals")
"""The figures' file stems; each is written as ``.png`` and ``.svg``."""
FORMATS = ("png", "svg")


def _methods(summary: dict[str, Any]) -> list[tuple[str, list[str]]]:
    """``(group, run labels)`` of the drivers benchmarked, in the user's order (ceiling and floor left out)."""
    return [(g["group"], list(g["runs"])) for g in summary["groups"]]


def normalised_bars(summary: dict[str, Any]) -> dict[str, Any]:
    """The numbers of ``bench_normalised``: ``{"roads": [...], "methods": [...], "value": (M, R), "low": (M, R),
    "high": (M, R)}`` (arrays of the methods' mean normalised score per road and its interval)."""
    roads = [r["scenario"] for r in summary["scenarios"]]
    methods = _methods(summary)
    shape = (len(methods), len(roads))
    value, low, high = np.full(shape, np.nan), np.full(shape, np.nan), np.full(shape, np.nan)
    for j, row in enumerate(summary["scenarios"]):
        drivers = row["drivers"]
        ceiling = next(iter(drivers.values()))["success_rate"]  # the ceiling is the first driver of every row
        for i, (_, runs) in enumerate(methods):
            norm = [drivers[r]["normalised"] for r in runs]
            value[i, j] = float(np.mean(norm))
            if len(runs) > 1:
                low[i, j], high[i, j] = t_interval(norm)
            elif ceiling > 0:
                lo, hi = drivers[runs[0]]["success_wilson95"]
                low[i, j], high[i, j] = lo / ceiling, hi / ceiling
    return {"roads": roads, "methods": [m for m, _ in methods], "value": value, "low": low, "high": high}


def _save(fig: Any, out: Path, stem: str, root: Path | None) -> list[Path]:
    import io

    from lckit.fileio import write_file

    paths = []
    for fmt in FORMATS:
        buf = io.BytesIO()
        fig.savefig(buf, format=fmt, dpi=110, bbox_inches="tight", metadata={"Date": None} if fmt == "svg" else None)
        paths.append(write_file(out / f"{stem}.{fmt}", buf.getvalue(), root=root))  # never through a link
    return paths


def write_figures(summary: dict[str, Any], out: str | Path, *, root: str | Path | None = None) -> list[Path]:
    """Write :data:`FIGURES` of ``summary`` into ``out`` (PNG and SVG each; never through a link, nor out of
    ``root`` when given); returns the paths written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    root = Path(root) if root is not None else None
    written: list[Path] = []
    bars = normalised_bars(summary)
    m, r = bars["value"].shape
    colors = plt.get_cmap("tab10")
    fig, ax = plt.subplots(figsize=(max(6.0, 1.1 * r * max(1, m) ** 0.5 + 2), 3.6))
    width = 0.8 / max(m, 1)
    x = np.arange(r)
    for i, name in enumerate(bars["methods"]):
        v = bars["value"][i]
        err = np.vstack((v - bars["low"][i], bars["high"][i] - v))
        ax.bar(x + (i - (m - 1) / 2) * width, v, width, yerr=np.nan_to_num(err), capsize=2, color=colors(i % 10),
               label=name)
    ax.axhline(1.0, color="black", lw=0.8, ls="--")
    ax.set_xticks(x, bars["roads"], rotation=20)
    ax.set_ylabel("normalised score (success / oracle's)")
    ax.set_ylim(0, 1.15)
    ax.set_title(f"Suite {summary['suite']}: {summary['split']} episodes")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 1.0))  # beside the bars, never over them
    written += _save(fig, out, FIGURES[0], root)
    plt.close(fig)

    agg = [g for g in summary["groups"] if "aggregate" in g]
    fig, axes = plt.subplots(1, 2, figsize=(7.5, 0.45 * max(len(agg), 2) + 1.2), sharey=True)
    for ax, key, title in zip(axes, ("iqm", "mean"), ("IQM", "Mean"), strict=True):
        for i, g in enumerate(agg):
            a = g["aggregate"][key]
            if a["ci95"]:
                ax.barh(i, a["ci95"][1] - a["ci95"][0], left=a["ci95"][0], height=0.6, color=colors(i % 10), alpha=0.75)
            ax.plot([a["value"]], [i], marker="|", markersize=14, color="black")
        ax.set_title(title)
        ax.set_xlabel("normalised score")
        ax.grid(axis="x", alpha=0.3)
    axes[0].set_yticks(range(len(agg)), [g["group"] for g in agg])
    fig.suptitle("Over runs and roads: stratified-bootstrap 95% intervals", fontsize=9)
    written += _save(fig, out, FIGURES[1], root)
    plt.close(fig)
    return written


def figures_markdown(stems: Sequence[str] = FIGURES) -> str:
    """The Markdown that embeds the figures beside BENCH.md (the SVGs)."""
    return "\n".join(f"![{s}]({s}.svg)" for s in stems) + "\n"


__all__ = ["FIGURES", "figures_markdown", "normalised_bars", "write_figures"]
