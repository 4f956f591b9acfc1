"""Files written whole or not at all (``sdh2svc.files.whole_file``)."""

from __future__ import annotations

from pathlib import Path

import pytest

from sdh2svc.files import whole_file


def test_a_file_is_written_whole_and_replaces_an_earlier_one(tmp_path: Path) -> None:
    target = tmp_path / "run.csv"
    target.write_text("earlier")
    with whole_file(target, binary=False) as f:
        f.write("new")
        assert target.read_text() == "earlier"  # not until it is complete
    assert target.read_text() == "new"
    assert [p.name for p in tmp_path.iterdir()] == ["run.csv"]


def test_an_interrupted_write_leaves_the_earlier_file_and_nothing_else(tmp_path: Path) -> None:
    target = tmp_path / "run.csv"
    target.write_text("earlier")
    with pytest.raises(KeyboardInterrupt), whole_file(target, binary=True) as f:
        f.write(b"half")
        raise KeyboardInterrupt
    assert target.read_text() == "earlier"
    assert [p.name for p in tmp_path.iterdir()] == ["run.csv"]


def test_a_file_that_cannot_be_created_is_named_as_asked_not_its_hidden_part(
    tmp_path: Path,
) -> None:
    target = tmp_path / "no such folder" / "run.csv"
    with pytest.raises(FileNotFoundError) as info, whole_file(target, binary=True):
        pass
    assert info.value.filename == str(target)
    assert ".part" not in str(info.value)
