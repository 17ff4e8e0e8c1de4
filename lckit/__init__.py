"""lckit: the small kit at the bottom of the stack that every package of the project may import.

- :mod:`lckit.config`: frozen, validated dataclass configs read from and written to TOML and JSON
  (:class:`~lckit.config.JsonConfig`, :func:`~lckit.config.read_data_file`).
- :mod:`lckit.fileio`: hashing, JSON, output-folder checks and locks, and the one way the project writes and
  deletes files (:func:`~lckit.fileio.write_file`, :func:`~lckit.fileio.remove_tree`): never through a symbolic
  link it did not make, never out of the folder it owns.
- :mod:`lckit.pool`: one process pool for every command that fans out (:class:`~lckit.pool.WorkerPool`):
  workers die with their parent, ignore Ctrl-C and run one thread each.

It imports no other package of the project and nothing heavy (no numpy, torch or numba).
"""
