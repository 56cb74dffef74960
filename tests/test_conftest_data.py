"""The rule for data tests (tests/conftest.py): skip without the shared data sets, fail
when they are required."""

from __future__ import annotations

import pytest

import conftest


def test_missing_data_skips_without_shared_and_fails_when_required(tmp_path, monkeypatch):
    monkeypatch.setattr(conftest, "DATASETS", tmp_path / "datasets")
    monkeypatch.delenv("EIFSLAM_REQUIRE_DATA", raising=False)
    with pytest.raises(pytest.skip.Exception, match="some-set"):
        conftest.dataset_path("some-set")
    monkeypatch.setenv("EIFSLAM_REQUIRE_DATA", "1")
    with pytest.raises(pytest.fail.Exception, match="required"):
        conftest.dataset_path("some-set")
    monkeypatch.delenv("EIFSLAM_REQUIRE_DATA")
    (tmp_path / "datasets").mkdir()  # the shared folder is there: a missing set fails
    with pytest.raises(pytest.fail.Exception, match="some-set"):
        conftest.dataset_path("some-set")
    (tmp_path / "datasets" / "some-set").mkdir()
    assert conftest.dataset_path("some-set") == tmp_path / "datasets" / "some-set"
