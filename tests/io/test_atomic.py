"""Atomic writes: a failure at any point leaves the old file as it was and no temporary file."""

import os

import pytest

from tissuefit.io import atomic_writer, write_json, write_text_atomic


def test_writes_and_replaces(tmp_path):
    path = tmp_path / "a.txt"
    write_text_atomic(path, "one\n")
    write_text_atomic(path, "two\n")
    assert path.read_text() == "two\n"
    assert os.listdir(tmp_path) == ["a.txt"]


def test_serialisation_failure_leaves_old_file(tmp_path):
    path = tmp_path / "r.json"
    write_json(path, {"rd": 0.25})
    before = path.read_bytes()
    with pytest.raises(TypeError):
        write_json(path, {"rd": object()})
    with pytest.raises(ValueError):  # NaN is not JSON
        write_json(path, {"rd": float("nan")})
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["r.json"]


def test_failure_while_writing_leaves_old_file(tmp_path):
    path = tmp_path / "big.txt"
    path.write_text("old")
    with pytest.raises(RuntimeError), atomic_writer(path) as handle:
        handle.write("half of the new content")
        raise RuntimeError("disk full")
    assert path.read_text() == "old"
    assert os.listdir(tmp_path) == ["big.txt"]


def test_failed_rename_leaves_old_file(tmp_path, monkeypatch):
    path = tmp_path / "x.txt"
    path.write_text("old")

    def refuse(src, dst):
        raise PermissionError("no")

    monkeypatch.setattr(os, "replace", refuse)
    with pytest.raises(PermissionError):
        write_text_atomic(path, "new")
    monkeypatch.undo()
    assert path.read_text() == "old"
    assert os.listdir(tmp_path) == ["x.txt"]


def test_new_file_gets_ordinary_permissions(tmp_path):
    path = tmp_path / "p.txt"
    write_text_atomic(path, "x")
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask


def test_a_folder_in_the_way_is_refused_before_writing_and_named(tmp_path):
    """Issue 25, tried by hand: a folder where the file goes failed only at the rename, with an error
    naming the temporary file (".preview.png.1a2b3c4d.tmp: Is a directory")."""
    (tmp_path / "preview.png").mkdir()
    with pytest.raises(IsADirectoryError) as caught:
        write_text_atomic(tmp_path / "preview.png", "x")
    assert caught.value.filename == str(tmp_path / "preview.png")
    assert sorted(os.listdir(tmp_path)) == ["preview.png"]
