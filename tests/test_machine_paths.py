"""No committed file names a folder of the machine it was made on (``/work/...``, ``/home/...``, ``/root/...``,
``/tmp/...``): a path in a document, card or record is written relative (``runs/...``, ``zoo/...``, a recipe's
name), so that it means the same in anyone's checkout.

Read: every file git tracks outside tests/ (whose fixtures name such paths on purpose). Left as made, because
their bytes are an identity that rewriting would change:

- a file whose SHA-256 another tracked file records (an experiment's stage record keeps the digest of each
  output, ``metrics.json`` and ``dagger.json`` among them; ``warm_start.json`` the digest of the policy it
  started from);
- binary files (policy weights, images, recordings): a policy file is known by its file digest to the
  experiments that evaluate it, and the training record in its header is read by nobody (the predictor path
  there is only a hint, found again by its SHA-256); its ``policy.card.json`` beside it, the card people read,
  is rewritten like any other text.
"""

from __future__ import annotations

import hashlib
import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
MACHINE_PATH = re.compile(r"(^|[^A-Za-z0-9_.])/(work|home|root|tmp)/[A-Za-z]", re.M)
DIGEST = re.compile(rb"\b[0-9a-f]{64}\b")


def tracked() -> list[str]:
    """The files git tracks (the test skips without git or outside a checkout)."""
    try:
        done = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z"], capture_output=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        pytest.skip("no git to list the tracked files")
    if done.returncode != 0:
        pytest.skip("not a git checkout")
    return [n for n in done.stdout.decode().split("\0") if n]


def binary(data: bytes) -> bool:
    return b"\0" in data[:8192]


def carrying_machine_paths(files: dict[str, bytes]) -> list[str]:
    """The text files of ``files`` (name -> bytes) outside tests/ that name a machine path, but for those whose
    SHA-256 one of ``files`` records."""
    recorded = {d.decode() for data in files.values() if not binary(data) for d in DIGEST.findall(data)}
    found = []
    for name, data in sorted(files.items()):
        if name.startswith("tests/") or binary(data):
            continue
        if MACHINE_PATH.search(data.decode("utf-8", errors="replace")) and (
            hashlib.sha256(data).hexdigest() not in recorded
        ):
            found.append(name)
    return found


def test_no_committed_file_names_a_folder_of_the_machine():
    files = {}
    for name in tracked():
        path = ROOT / name
        if path.is_file() and not path.is_symlink():
            files[name] = path.read_bytes()
    found = carrying_machine_paths(files)
    assert found == [], ("these files name a folder of the machine they were made on; write the path relative "
                         "(runs/..., zoo/..., the recipe's name):\n" + "\n".join(found))  # fmt: skip


def test_what_counts_as_a_machine_path():
    record = b'{"init_policy": "/work/main/runs/a/policy.safetensors"}'
    files = {
        "docs/a.md": b"lc-eval /home/me/policy.safetensors",
        "docs/b.json": b'{"checkpoint": "/tmp/ptw/predictor.pt"}',
        "docs/c.md": b"runs/work/x, zoo/tmp/y, /workspace, /tmp/1, $HOME/x, ../root/z",
        "docs/d.json": record,
        "docs/stage.json": b'{"outputs": {"metrics.json": "' + hashlib.sha256(record).hexdigest().encode() + b'"}}',
        "docs/e.bin": b"\0\0/work/main/x",
        "tests/fixture.txt": b"/root/x",
    }
    assert carrying_machine_paths(files) == ["docs/a.md", "docs/b.json"]
    assert carrying_machine_paths({**files, "docs/stage.json": b"{}"}) == ["docs/a.md", "docs/b.json", "docs/d.json"]
