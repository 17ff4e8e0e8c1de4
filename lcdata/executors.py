"""Where independent pieces of work run: in this machine's processes (``local``) or as Ray tasks (``ray``).

Ray (``pip install -e ".[ray]"``) runs a task on any machine of a cluster it is connected to: a running
cluster (``address``, or ``RAY_ADDRESS``) or a local one it starts for the session. Every task writes its
files itself, so on a cluster the output directory must be on storage that every node sees (NFS, a shared
volume). A task gets the functions and arguments it runs pickled by Ray: the project passes only names,
paths, seeds and configs as JSON, never a loaded model. Without Ray installed, asking for it is one
``ValueError`` that says how to install it.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any

EXECUTORS = ("local", "ray")
"""What ``--executor`` accepts."""
RAY_MISSING = "--executor ray needs Ray, which is not installed: pip install -e \".[ray]\""


def ray_module() -> Any:
    """The ``ray`` package; ``ValueError`` with the install command when it is missing."""
    try:
        import ray
    except ImportError:
        raise ValueError(RAY_MISSING) from None
    return ray


@contextlib.contextmanager
def ray_session(address: str | None = None, num_cpus: int | None = None) -> Iterator[Any]:
    """Ray connected for the block: to ``address`` (or ``RAY_ADDRESS``) when given, else a local instance
    started with ``num_cpus`` CPUs (all by default) and shut down afterwards. A session already open in this
    process is reused and left open."""
    ray = ray_module()
    if ray.is_initialized():
        yield ray
        return
    address = address or os.environ.get("RAY_ADDRESS") or None
    kwargs: dict[str, Any] = {"include_dashboard": False, "log_to_driver": True, "configure_logging": False}
    if address is None:
        kwargs["num_cpus"] = num_cpus
    try:
        ray.init(address=address, **kwargs)
    except (ConnectionError, RuntimeError, ValueError) as exc:
        raise ValueError(f"could not start or reach Ray ({address or 'a local instance'}): "
                         f"{' '.join(str(exc).split())[:200]}") from None
    try:
        yield ray
    finally:
        ray.shutdown()


def ray_map(fn: Callable[..., Any], calls: Sequence[tuple[Any, ...]], *, num_cpus: float = 1.0) -> Iterator[Any]:
    """Run ``fn(*args)`` for each ``args`` of ``calls`` as Ray tasks (``num_cpus`` each) in an open
    :func:`ray_session`; yields the results as they complete. A failed task's exception is raised here and
    the tasks not yet finished are cancelled."""
    ray = ray_module()
    remote = ray.remote(num_cpus=num_cpus, max_retries=0)(fn)
    pending = [remote.remote(*args) for args in calls]
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            yield ray.get(done[0])
    finally:
        for ref in pending:
            with contextlib.suppress(Exception):
                ray.cancel(ref, force=True)


def shards(items: Sequence[Any], count: int) -> list[list[Any]]:
    """``items`` cut into at most ``count`` contiguous, nearly equal, non-empty parts, in order."""
    count = max(1, min(count, len(items)))
    size, extra = divmod(len(items), count)
    out, start = [], 0
    for i in range(count):
        end = start + size + (i < extra)
        out.append(list(items[start:end]))
        start = end
    return [s for s in out if s]
