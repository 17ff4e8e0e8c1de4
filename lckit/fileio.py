"""The project's file helpers (no heavy imports): hashing, JSON, checks of an output folder, its lock, and the
one way every command writes and deletes in a folder it owns.

Writing and deleting never follow a symbolic link the project did not make (and it makes none):

- :func:`write_file` writes ``NAME.partial``, created new (``O_CREAT | O_EXCL | O_NOFOLLOW``), and renames it
  over ``NAME``; it refuses a ``NAME`` or ``NAME.partial`` that is a link, and with ``root`` (the command's
  ``--out``) a folder whose real path leads out of it. :func:`open_partial` is its first half, for a file
  written as a stream (an MCAP recording).
- :func:`remove_tree` and :func:`remove_file` delete below ``root`` only: a link goes as a link (never its
  target's contents), and ``rmtree`` does not follow the links inside.
- :func:`check_inside` is the test both use, and what a path read back from a file (a stage record, a round
  of DAgger, a zoo name) is checked with before it is opened.

A refusal is an :class:`UnsafePathError` (an ``OSError``) with a one-line message naming the path.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import shutil
import stat
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

PARTIAL_SUFFIX = ".partial"
"""What a file is called while it is written (``NAME.partial``, renamed to ``NAME`` when complete)."""


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


def write_json(path: str | os.PathLike[str], data: Any, *, root: str | os.PathLike[str] | None = None) -> None:
    """Write ``data`` as indented JSON with :func:`write_file` (``root``: the folder it must stay in)."""
    write_file(path, json.dumps(data, indent=2, sort_keys=True, default=json_default) + "\n", root=root)


# ------------------------------------------------------------------------------ writing and deleting safely
class UnsafePathError(OSError):
    """A path the project does not write, delete or read through: a symbolic link it did not make, or a real
    path outside the folder it belongs in. Its message is one line naming the path."""


def _real(path: str | os.PathLike[str]) -> Path:
    return Path(os.path.realpath(path))


def check_inside(path: str | os.PathLike[str], root: str | os.PathLike[str], what: str = "") -> Path:
    """``path`` (as given) when its real path, every symbolic link and ``..`` resolved (parts that do not exist
    yet taken as they are), lies in ``root``'s real path or is it; else :class:`UnsafePathError` naming
    ``what`` (default: the path) and where it leads."""
    real, base = _real(path), _real(root)
    if real != base and base not in real.parents:
        raise UnsafePathError(f"{what or path} leads out of {root} (to {real}); refusing to follow it")
    return Path(path)


def _refuse_link(path: Path) -> None:
    if path.is_symlink():
        raise UnsafePathError(f"{path} is a symbolic link, which this project never makes; refusing to write "
                              "through it (remove it)")


def check_target(path: str | os.PathLike[str], root: str | os.PathLike[str] | None = None) -> Path:
    """``path`` when :func:`write_file` may write it: neither ``path`` nor ``path.partial`` is a symbolic link,
    and (with ``root``) the real path of its folder is in ``root``'s; else :class:`UnsafePathError`. A command
    checks its files with it before any work; the writers check again."""
    path = Path(path)
    if root is not None:
        check_inside(path.parent, root)
    _refuse_link(path)
    _refuse_link(path.with_name(path.name + PARTIAL_SUFFIX))
    return path


def make_folder(path: str | os.PathLike[str], root: str | os.PathLike[str] | None = None) -> Path:
    """``mkdir -p path``; with ``root``, only when the folder's real path is in ``root`` (checked before and after,
    :func:`check_inside`): a link on the way that leads elsewhere is refused, not written through."""
    path = Path(path)
    if root is not None:
        check_inside(path, root)
    path.mkdir(parents=True, exist_ok=True)
    if root is not None:
        check_inside(path, root)
    return path


def open_partial(path: str | os.PathLike[str], *, root: str | os.PathLike[str] | None = None) -> IO[bytes]:
    """``path.partial`` opened for writing, created new (``O_EXCL | O_NOFOLLOW``; a killed run's regular file of
    that name is removed first); rename it over ``path`` with ``os.replace`` when complete. Refuses
    (:class:`UnsafePathError`) when ``path`` or ``path.partial`` is a symbolic link, or ``path``'s folder leads
    out of ``root``. The folder must exist."""
    partial = check_target(path, root).with_name(Path(path).name + PARTIAL_SUFFIX)
    with contextlib.suppress(FileNotFoundError):
        if stat.S_ISREG(os.lstat(partial).st_mode):
            os.unlink(partial)
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    return os.fdopen(os.open(partial, flags, 0o666), "wb")


def write_file(path: str | os.PathLike[str], content: bytes | str | Callable[[Any], object], *,
               root: str | os.PathLike[str] | None = None, by_name: bool = False,
               errors: tuple[type[BaseException], ...] = ()) -> Path:  # fmt: skip
    """Write the file ``path`` atomically and never through a link: ``content`` (bytes, text as UTF-8, or a
    function writing it: given the open binary file, or with ``by_name`` the ``.partial`` file's path, for a
    library that opens a file by name) goes to ``path.partial`` (:func:`open_partial`), renamed over ``path``
    when complete. The folder is made (below ``root`` only, :func:`make_folder`). Returns ``path``.

    A write that fails (a full disk, which torch reports as a ``RuntimeError`` and a library may as ``errors``)
    raises ``OSError`` naming ``path`` and leaves no ``.partial`` behind; the file at ``path`` is as it was. A
    link in the way is an :class:`UnsafePathError`, with nothing written."""
    path = Path(path)
    make_folder(path.parent, root)
    f = open_partial(path, root=root)
    partial = path.with_name(path.name + PARTIAL_SUFFIX)
    try:
        with f:
            if isinstance(content, str):
                content = content.encode()
            if isinstance(content, bytes | bytearray | memoryview):
                f.write(content)
            elif by_name:
                content(str(partial))
                mine, there = os.fstat(f.fileno()), os.lstat(partial)
                if (mine.st_dev, mine.st_ino) != (there.st_dev, there.st_ino) or not stat.S_ISREG(there.st_mode):
                    raise UnsafePathError(f"{partial} was replaced while it was written; refusing to use it")
            else:
                content(f)
        os.replace(partial, path)
    except (OSError, RuntimeError, *errors) as exc:
        with contextlib.suppress(OSError):
            os.unlink(partial)
        if isinstance(exc, OSError):
            raise
        detail = " ".join(str(exc).split())[:200]
        raise OSError(f"could not write {path}: {detail}") from None
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(partial)
        raise
    return path


def remove_file(path: str | os.PathLike[str], root: str | os.PathLike[str], *, missing_ok: bool = True) -> None:
    """Delete the file ``path`` (a link as the link itself, never its target) when its folder's real path is in
    ``root`` (:func:`check_inside`; else :class:`UnsafePathError`, nothing deleted)."""
    path = Path(path)
    check_inside(path.parent, root)
    try:
        os.unlink(path)
    except FileNotFoundError:
        if not missing_ok:
            raise


def remove_tree(path: str | os.PathLike[str], root: str | os.PathLike[str]) -> None:
    """Delete ``path`` and everything below it, below ``root`` only: a link (``path`` itself or one inside) goes
    as a link, never its target's contents; :class:`UnsafePathError` when ``path``'s folder leads out of
    ``root`` or ``path`` is ``root`` itself. Missing: nothing to do."""
    path = Path(path)
    check_inside(path.parent, root)
    if not path.is_symlink() and _real(path) == _real(root):
        raise UnsafePathError(f"refusing to delete {path}: it is the folder {root} itself")
    if path.is_symlink() or (path.exists() and not path.is_dir()):
        path.unlink()
    elif path.exists():
        if not shutil.rmtree.avoids_symlink_attacks:  # pragma: no cover - every POSIX system with openat
            raise UnsafePathError(f"refusing to delete {path}: this system's rmtree may follow links")
        shutil.rmtree(path)


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
    path = Path(folder) / name
    _refuse_link(path)
    flags = os.O_RDWR | os.O_CREAT | os.O_APPEND | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    with os.fdopen(os.open(path, flags, 0o666), "a+") as fh:
        held = os.fstat(fh.fileno())
        if not stat.S_ISREG(held.st_mode) or held.st_nlink != 1:  # the pid is written in it: no one else's file
            raise UnsafePathError(f"{path} is not a lock file of this project (a special file or a hard link); "
                                  "remove it")
        deadline = time.monotonic() + max(0.0, wait_s)
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
