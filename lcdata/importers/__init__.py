"""Traffic recorded elsewhere -> episodes of the trajectory corpus (what ``lc-record --scenario corpus``
writes and :func:`lcdata.corpus.load_tracks` reads).

Formats: SUMO floating car data (:func:`import_sumo_fcd`, :mod:`lcdata.importers.sumo`) and the highD
drone-track layout (:func:`import_highd`, :mod:`lcdata.importers.highd`). Every import

- converts positions to the vehicle's centre in the corpus frame (x forward, y left, yaw counter-clockwise
  from +x, lane 0 the rightmost; ids from 1, as there is no ego);
- resamples onto the corpus grid, 20 Hz unless :attr:`ImportOptions.dt_s` says otherwise, by linear
  interpolation between source samples (:mod:`lcdata.importers.resample`);
- cuts the recording into episodes of :attr:`ImportOptions.episode_steps` steps (2000, the corpus length),
  each one ``.mcap`` file written by :class:`lcdata.writer.EpisodeWriter` with ``/vehicles`` only (no ego
  state, scene or image) and the metadata ``source_format``, ``source_file``, ``source_sha256``,
  ``source_start_s``, ``episode_index`` and ``vehicles`` (the source id of every vehicle id);
- writes the same bytes for the same input and options, and writes all its files or none.

::

    from lcdata.importers import import_highd
    episodes = import_highd("highD/data/01_tracks.csv", "data/highd")   # 01_tracksMeta.csv beside it
    tracks = lcdata.corpus.load_tracks("data/highd")
"""

from lcdata.importers.episodes import CORPUS_DT_S, CORPUS_EPISODE_STEPS, ImportedEpisode, ImportOptions
from lcdata.importers.highd import HighdOptions, import_highd
from lcdata.importers.sumo import SumoOptions, import_sumo_fcd

FORMATS = ("sumo-fcd", "highd")
"""The formats there is an importer for (the names ``lc-import`` takes)."""

__all__ = [
    "CORPUS_DT_S",
    "CORPUS_EPISODE_STEPS",
    "FORMATS",
    "HighdOptions",
    "ImportOptions",
    "ImportedEpisode",
    "SumoOptions",
    "import_highd",
    "import_sumo_fcd",
]
