"""Recorded episodes in Rerun: the library behind ``lc-view`` (:mod:`lcdata.viewer.app`)."""

from lcdata.viewer.app import ViewError, convert, make_recordings, open_episodes, serve

__all__ = ["ViewError", "convert", "make_recordings", "open_episodes", "serve"]
