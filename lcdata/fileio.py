"""Small file helpers shared by recording, the policy runs and the experiment pipeline (no heavy imports)."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any


def file_sha256(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's content, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def json_default(o: Any) -> Any:
    """``json.dumps`` fallback: numpy arrays and scalars, paths, other numbers."""
    if hasattr(o, "tolist"):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    return float(o)


def loads_json(text: str | bytes) -> Any:
    """``json.loads``, with nesting too deep for the parser a ``ValueError`` too, not a ``RecursionError``
    (:func:`lckit.config.loads_data`, what every config file is read with)."""
    from lckit.config import loads_data

    return loads_data(text, ".json")


def read_json(path: str | os.PathLike[str]) -> Any | None:
    """The JSON in ``path``, or None when it is missing, unreadable or not valid JSON (too deep included)."""
    try:
        return loads_json(Path(path).read_text())
    except (OSError, ValueError):  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        return None


def write_json(path: str | os.PathLike[str], data: Any) -> None:
    """Write ``data`` as indented JSON atomically (``.partial`` then rename), creating the directory. A write
    that fails (a full disk) leaves no ``.partial`` behind and the file as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    try:
        tmp.write_text(json.dumps(data, indent=2, sort_keys=True, default=json_default) + "\n")
        tmp.replace(path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_atomically(tmp: str | os.PathLike[str], path: str | os.PathLike[str], write: Callable[[], object], *,
                     errors: tuple[type[BaseException], ...] = ()) -> None:
    """``write()`` the file ``tmp``, then rename it to ``path``. A write that fails (a full disk, which torch
    reports as a ``RuntimeError`` and a library may as ``errors``) raises ``OSError`` naming ``path`` and leaves
    no ``tmp`` behind; the file at ``path`` is as it was."""
    tmp = Path(tmp)
    try:
        write()
        tmp.replace(path)
    except (OSError, RuntimeError, *errors) as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError):
            raise
        detail = " ".join(str(exc).split())[:200]
        raise OSError(f"could not write {path}: {detail}") from None


def refused_folder(path: str | os.PathLike[str]) -> str:
    """Why ``path`` must not be a command's output folder (``""`` when it may be): the filesystem root, or the
    home directory itself (a command would scatter its files among the user's own, and ``--overwrite`` would
    reach them). Symbolic links and ``..`` are resolved first."""
    try:
        where = Path(path).expanduser().resolve()
    except (OSError, RuntimeError):
        return ""
    if where == Path(where.anchor):
        return "is the filesystem root"
    with contextlib.suppress(KeyError, RuntimeError, OSError):
        if where == Path.home().resolve():
            return "is the home directory itself"
    return ""


def _probe(folder: Path) -> str:
    """Why nothing can be written in the existing directory ``folder`` (``""`` when a file can): a file is made
    and removed there, which is what the permission bits, a read-only mount or a root-owned tree decide alike."""
    try:
        with tempfile.NamedTemporaryFile(dir=folder, prefix=".lc-probe-"):
            pass
    except OSError as exc:
        return exc.strerror or type(exc).__name__
    return ""


def check_output_folder(path: str | os.PathLike[str], flag: str = "--out") -> None:
    """``ValueError`` in one line, before any work, when the folder ``path`` cannot take a command's output: it
    is the filesystem root or the home directory (:func:`refused_folder`), a file, or it (or the nearest folder
    above it that exists, where it is to be made) cannot be written. Nothing is created."""
    path = Path(path)
    why = refused_folder(path)
    if why:
        raise ValueError(f"{flag} {path} {why}; name a folder for this output")
    if path.exists() and not path.is_dir():
        raise ValueError(f"{flag} {path} exists and is not a directory")
    folder = path
    while not folder.exists():
        if folder.is_symlink() or folder.parent == folder:
            raise ValueError(f"{flag} {path}: cannot create output directory ({folder} is a dangling link)")
        folder = folder.parent
    if not folder.is_dir():
        raise ValueError(f"{flag} {path}: cannot create output directory ({folder} is a file)")
    problem = _probe(folder)
    if problem:
        raise ValueError(f"{flag} {path} cannot be written ({folder}: {problem})")


def check_output_file(path: str | os.PathLike[str], flag: str) -> None:
    """``ValueError`` in one line, before any work, when the file ``path`` cannot be written later: it is a
    directory, or its folder (or the nearest one above it that exists) cannot be written. Nothing is created."""
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{flag} {path} is a directory; name a file")
    check_output_folder(path.parent if str(path.parent) else Path("."), flag=f"{flag} {path}: its folder")


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike[str], what: str, name: str = ".lock",
                doing: str = "is writing in", wait_s: float = 0.0) -> Iterator[None]:
    """Hold ``folder/name`` (an advisory ``flock``, released however the process ends) while a command writes in
    ``folder``: a second command there gets a one-line ``ValueError`` naming the holder's pid instead of two
    writers interleaving their files, after waiting up to ``wait_s`` seconds for the holder to let go (a holder
    that keeps the lock only for a moment). ``folder`` must exist. Not POSIX: no lock."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    import time

    deadline = time.monotonic() + max(0.0, wait_s)
    with open(Path(folder) / name, "a+") as fh:
        while True:
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() < deadline:
                    time.sleep(0.05)
                    continue
                fh.seek(0)
                holder = fh.read(32).strip() or "unknown"
                raise ValueError(f"another {what} (pid {holder}) {doing} {folder}; wait for it to finish or stop "
                                 "it first") from None
        fh.seek(0)
        fh.truncate()
        fh.write(str(os.getpid()))
        fh.flush()
        try:
            yield
        finally:
            with contextlib.suppress(OSError):
                fh.seek(0)
                fh.truncate()
            fcntl.flock(fh, fcntl.LOCK_UN)
