"""``lc-view``: recorded episodes in Rerun. The command line lives in :mod:`lcdata.viewer.cli`."""

from lcdata.viewer.cli import ViewError, build_parser, convert, main, make_recordings, open_episodes, serve

__all__ = ["ViewError", "build_parser", "convert", "main", "make_recordings", "open_episodes", "serve"]
