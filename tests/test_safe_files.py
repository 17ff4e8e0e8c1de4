"""The one way the project writes and deletes (:mod:`lckit.fileio`): never through a symbolic link it did not
make, never out of the folder it owns."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from lckit.fileio import (
    UnsafePathError,
    check_inside,
    folder_lock,
    make_folder,
    remove_file,
    remove_tree,
    write_file,
    write_json,
)


@pytest.fixture
def victim(tmp_path: Path) -> Path:
    """A file somewhere else that a link in the output folder points at."""
    (tmp_path / "elsewhere").mkdir()
    path = tmp_path / "elsewhere" / "thesis.tex"
    path.write_text("years of work")
    return path


def test_a_file_is_written_atomically_and_a_killed_runs_partial_is_replaced(tmp_path: Path) -> None:
    out = tmp_path / "out"
    (out / "sub").mkdir(parents=True)
    (out / "sub" / "a.json.partial").write_text("half a file from a killed run")
    write_json(out / "sub" / "a.json", {"x": 1}, root=out)
    assert (out / "sub" / "a.json").read_text() == '{\n  "x": 1\n}\n'
    assert not (out / "sub" / "a.json.partial").exists()
    write_file(out / "b.bin", lambda f: f.write(b"\x00\x01"))
    write_file(out / "c.txt", lambda name: Path(name).write_text("by name"), by_name=True)
    assert (out / "b.bin").read_bytes() == b"\x00\x01" and (out / "c.txt").read_text() == "by name"


@pytest.mark.parametrize("link", ["a.json", "a.json.partial"])
def test_a_link_at_the_file_or_its_partial_is_refused_and_its_target_kept(tmp_path: Path, victim: Path,
                                                                         link: str) -> None:  # fmt: skip
    out = tmp_path / "out"
    out.mkdir()
    (out / link).symlink_to(victim)
    with pytest.raises(UnsafePathError, match="symbolic link"):
        write_json(out / "a.json", {"x": 1}, root=out)
    assert victim.read_text() == "years of work"
    assert (out / link).is_symlink()  # the user's link stays too


def test_a_hard_linked_partial_is_replaced_not_written_into(tmp_path: Path, victim: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    os.link(victim, out / "a.txt.partial")
    write_file(out / "a.txt", "mine")
    assert (out / "a.txt").read_text() == "mine" and victim.read_text() == "years of work"


def test_a_folder_that_leads_out_of_the_root_is_refused(tmp_path: Path, victim: Path) -> None:
    out = tmp_path / "out"
    out.mkdir()
    (out / "stage").symlink_to(victim.parent)
    for write in (lambda: write_json(out / "stage" / "thesis.tex", {}, root=out),
                  lambda: make_folder(out / "stage" / "deeper", out)):  # fmt: skip
        with pytest.raises(UnsafePathError, match="leads out of"):
            write()
    assert victim.read_text() == "years of work" and not (victim.parent / "deeper").exists()
    check_inside(out / "new" / "folder", out)  # what does not exist yet is inside
    (out / "inner").symlink_to(out / "new", target_is_directory=True)
    check_inside(out / "inner", out)  # a link that stays inside is no escape


def test_a_file_replaced_by_a_link_while_a_library_writes_it_by_name_is_refused(tmp_path: Path,
                                                                               victim: Path) -> None:  # fmt: skip
    def swap(name: str) -> None:
        os.unlink(name)
        os.symlink(victim, name)

    with pytest.raises(UnsafePathError, match="replaced"):
        write_file(tmp_path / "a.pt", swap, by_name=True)
    assert victim.read_text() == "years of work" and not (tmp_path / "a.pt").exists()
    assert not (tmp_path / "a.pt.partial").is_symlink()


def test_deleting_removes_a_link_as_a_link_and_never_leaves_the_root(tmp_path: Path, victim: Path) -> None:
    out = tmp_path / "out"
    (out / "stage" / "sub").mkdir(parents=True)
    (out / "stage" / "inner").symlink_to(victim.parent)
    (out / "stage" / "file").symlink_to(victim)
    (out / "linked").symlink_to(victim.parent)
    remove_tree(out / "stage", out)  # the links inside go as links
    remove_tree(out / "linked", out)  # a link to a folder goes as the link
    assert not (out / "stage").exists() and not (out / "linked").exists()
    assert victim.read_text() == "years of work"
    (out / "away").symlink_to(victim.parent)
    for delete in (lambda: remove_tree(out / "away" / "x", out), lambda: remove_file(out / "away" / "thesis.tex", out),
                   lambda: remove_tree(out, out), lambda: remove_tree(tmp_path / "elsewhere", out)):  # fmt: skip
        with pytest.raises(UnsafePathError):
            delete()
    assert victim.read_text() == "years of work"
    remove_file(out / "away", out)  # the link itself
    assert not (out / "away").exists() and victim.exists()


def test_a_lock_file_that_is_a_link_or_a_hard_link_is_refused(tmp_path: Path, victim: Path) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / ".lock").symlink_to(victim)
    (tmp_path / "b").mkdir()
    os.link(victim, tmp_path / "b" / ".lock")
    for folder in ("a", "b"):
        with pytest.raises(UnsafePathError), folder_lock(tmp_path / folder, "test"):
            pass
    assert victim.read_text() == "years of work"
    with folder_lock(tmp_path, "test"):
        assert (tmp_path / ".lock").read_text() == str(os.getpid())
