"""The command lines of lc-toolkit: ``lc-record``, ``lc-train-predictor``, ``lc-train-policy``, ``lc-eval``,
``lc-experiment`` and ``lc-view``.

The application layer: each command is a thin ``main(argv) -> int`` that turns flags into a config and
calls the libraries (``lcsim`` <- ``lcdata`` <- ``lcmodels``), so tests call it in-process; bad input ends
with one ``prog: error: ...`` line on stderr and exit status 2. Nothing below imports this package.
"""
