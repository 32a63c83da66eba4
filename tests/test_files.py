"""The one output guard and the one atomic write (elo_mitsuba.files)."""

import pytest

from elo_mitsuba.errors import EloInputError
from elo_mitsuba.files import atomic_write, check_output


def test_check_output_refuses_each_bad_path_in_one_line(tmp_path):
    (tmp_path / "old.exr").write_text("x")
    (tmp_path / "afile").write_text("x")
    (tmp_path / "adir.exr").mkdir()
    cases = [
        (tmp_path / "out.png", "must end in .exr"),
        (tmp_path / "old.exr", "exists; pass --overwrite"),
        (tmp_path / "adir.exr", "is a folder"),
        (tmp_path / "missing" / "out.exr", "does not exist"),
        (tmp_path / "afile" / "out.exr", "is a file, not a directory"),
    ]
    for path, message in cases:
        with pytest.raises(EloInputError, match=message) as err:
            check_output(path, (".exr",))
        assert "\n" not in str(err.value) and str(path) in str(err.value)
    assert check_output(tmp_path / "old.exr", (".exr",), overwrite=True) == tmp_path / "old.exr"
    assert check_output(tmp_path / "NEW.EXR", (".exr",)).name == "NEW.EXR"  # suffix case-insensitive


def test_atomic_write_keeps_the_old_file_and_no_temporary_on_failure(tmp_path):
    target = tmp_path / "result.npy"
    target.write_bytes(b"old")

    def fails(tmp):
        tmp.write_bytes(b"half")
        raise RuntimeError("disk full")

    with pytest.raises(RuntimeError):
        atomic_write(target, fails)
    assert target.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["result.npy"]
    seen = []
    atomic_write(target, lambda tmp: (seen.append(tmp.suffix), tmp.write_bytes(b"new")))
    assert target.read_bytes() == b"new" and seen == [".npy"]  # writers see the real suffix
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.npy"]
