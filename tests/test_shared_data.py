"""The skip/fail rules of tests/shared_data.py, on a temporary stand-in for ../shared."""

from __future__ import annotations

from pathlib import Path

import pytest

import shared_data
from shared_data import shared_available, shared_dir, shared_file, shared_path


@pytest.fixture
def shared(tmp_path, monkeypatch) -> Path:
    """A present ../shared with one good file, one empty file and one folder."""
    root = tmp_path / "shared"
    (root / "realdata" / "sample").mkdir(parents=True)
    (root / "realdata" / "sample" / "a.txt").write_text("data")
    (root / "realdata" / "sample" / "empty.txt").write_bytes(b"")
    monkeypatch.setattr(shared_data, "SHARED", root)
    return root


def test_shared_is_next_to_the_repository():
    repo = Path(__file__).resolve().parent.parent
    assert shared_data.SHARED == repo.parent / "shared"
    assert not shared_data.SHARED.is_relative_to(repo)


def test_absent_shared_skips(tmp_path, monkeypatch):
    monkeypatch.setattr(shared_data, "SHARED", tmp_path / "shared")
    assert not shared_available()
    with pytest.raises(pytest.skip.Exception, match="absent"):
        shared_file("realdata", "sample", "a.txt")
    with pytest.raises(pytest.skip.Exception, match="absent"):
        shared_dir("realdata", "sample")


def test_present_files_and_folders_are_returned(shared):
    assert shared_available()
    assert shared_file("realdata", "sample", "a.txt") == shared / "realdata" / "sample" / "a.txt"
    assert shared_file(Path("realdata/sample/a.txt")).read_text() == "data"
    assert shared_dir("realdata", "sample", files=["a.txt"]) == shared / "realdata" / "sample"
    assert shared_dir() == shared
    assert shared_path("x", "y") == shared / "x" / "y"  # no check


def test_missing_file_fails_and_names_it(shared):
    missing = shared / "realdata" / "sample" / "nope.png"
    with pytest.raises(pytest.fail.Exception, match=f"missing: {missing}"):
        shared_file("realdata", "sample", "nope.png")
    with pytest.raises(pytest.fail.Exception, match="missing: .*other"):
        shared_file("realdata", "other", "a.txt")


def test_missing_folder_fails_and_names_it(shared):
    with pytest.raises(pytest.fail.Exception, match=f"folder missing: {shared / 'realdata' / 'other'}"):
        shared_dir("realdata", "other")
    with pytest.raises(pytest.fail.Exception, match="missing: .*nope.json"):
        shared_dir("realdata", "sample", files=["a.txt", "nope.json"])


def test_empty_or_wrong_kind_fails(shared):
    with pytest.raises(pytest.fail.Exception, match="empty: .*empty.txt"):
        shared_file("realdata", "sample", "empty.txt")
    with pytest.raises(pytest.fail.Exception, match="empty: .*empty.txt"):
        shared_dir("realdata", "sample", files=["empty.txt"])
    with pytest.raises(pytest.fail.Exception, match="not a file"):
        shared_file("realdata", "sample")
    with pytest.raises(pytest.fail.Exception, match="not a folder"):
        shared_dir("realdata", "sample", "a.txt")


def test_shared_that_is_a_file_or_a_dangling_link_fails(tmp_path, monkeypatch):
    as_file = tmp_path / "shared_file"
    as_file.write_text("not a folder")
    monkeypatch.setattr(shared_data, "SHARED", as_file)
    with pytest.raises(pytest.fail.Exception, match="not a readable folder"):
        shared_file("realdata", "sample", "a.txt")
    dangling = tmp_path / "shared_link"
    dangling.symlink_to(tmp_path / "gone")
    monkeypatch.setattr(shared_data, "SHARED", dangling)
    assert shared_available()
    with pytest.raises(pytest.fail.Exception):
        shared_dir("realdata")


def test_unreadable_file_is_checked_by_reading(shared, monkeypatch):
    """An OSError on reading fails the test (simulated: CI runs as root, which reads
    files whatever their mode)."""
    real_open = Path.open

    def refuse(self, *args, **kwargs):
        if self.name == "a.txt":
            raise PermissionError(13, "Permission denied", str(self))
        return real_open(self, *args, **kwargs)

    monkeypatch.setattr(Path, "open", refuse)
    with pytest.raises(pytest.fail.Exception, match="unreadable: .*a.txt"):
        shared_file("realdata", "sample", "a.txt")


# -- in a fixture: the skip/fail reaches the tests that use it -------------------------

pytest_plugins = ["pytester"]


def test_in_a_fixture_absent_skips_and_missing_fails(pytester, tmp_path, monkeypatch):
    """A small test file run in an in-process sub-session (so it imports this very
    ``shared_data`` module, monkeypatched here): ../shared absent -> both tests skipped;
    present but without the file -> an error (fixture) and a failure (test), no skip."""
    pytester.syspathinsert(Path(shared_data.__file__).parent)
    pytester.makepyfile(
        test_inner="""
        import pytest
        from shared_data import shared_file

        @pytest.fixture(scope="module")
        def sample():
            return shared_file("realdata", "sample", "a.txt")

        def test_uses_fixture(sample):
            assert sample.read_text() == "data"

        def test_calls_directly():
            assert shared_file("realdata", "sample", "a.txt").read_text() == "data"
        """
    )
    root = tmp_path / "inner_shared"
    monkeypatch.setattr(shared_data, "SHARED", root)
    args = ("-p", "no:cacheprovider", "-p", "no:dash")
    pytester.runpytest_inprocess(*args).assert_outcomes(skipped=2)
    (root / "realdata").mkdir(parents=True)
    result = pytester.runpytest_inprocess(*args)
    result.assert_outcomes(errors=1, failed=1)
    result.stdout.fnmatch_lines(["*shared data file missing: *a.txt*"])
    (root / "realdata" / "sample").mkdir()
    (root / "realdata" / "sample" / "a.txt").write_text("data")
    pytester.runpytest_inprocess(*args).assert_outcomes(passed=2)
