"""Shared test fixtures and the rules for tests that read the shared data sets.

A test that reads ``../shared/datasets`` (beside the repository) is marked ``data`` and
finds its data set through the :func:`shared_dataset` fixture. When the data set is
missing or unreadable the test skips, except in CI mode: when the environment variable
``EIFSLAM_REQUIRE_DATA=1`` is set or ``../shared/datasets`` exists, it fails instead,
so that a checkout with the data never passes with its data tests silently skipped.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import pytest

#: The repository root (this file is ``tests/conftest.py``).
REPO = Path(__file__).resolve().parents[1]
#: The shared evaluation data sets, beside the repository.
DATASETS = REPO.parent / "shared" / "datasets"


def data_required() -> bool:
    """CI mode: ``EIFSLAM_REQUIRE_DATA=1`` is set or ``../shared/datasets`` exists."""
    return os.environ.get("EIFSLAM_REQUIRE_DATA") == "1" or DATASETS.is_dir()


def dataset_path(name: str) -> Path:
    """``../shared/datasets/<name>`` (a folder or a file in it); skips the calling test when
    it is missing or unreadable, or fails it in CI mode (:func:`data_required`)."""
    path = DATASETS / name
    readable = path.exists() and os.access(path, os.R_OK | (os.X_OK if path.is_dir() else 0))
    if not readable:
        msg = f"shared data set {name} is missing or unreadable at {path}"
        if data_required():
            pytest.fail(f"{msg} (data tests are required: EIFSLAM_REQUIRE_DATA=1 or {DATASETS} exists)")
        pytest.skip(msg)
    return path


@pytest.fixture
def shared_dataset() -> Callable[[str], Path]:
    """``shared_dataset("kitti-seq1")`` -> the data set's path, or a skip (a failure in CI
    mode) when it cannot be read; see :func:`dataset_path`."""
    return dataset_path


def _names_shared_data(item: pytest.Item) -> bool:
    return any("shared/datasets" in str(m.kwargs.get("reason", "")) for m in item.iter_markers("skipif"))


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """A test skipped on a condition that names ``../shared/datasets`` is a data test too."""
    for item in items:
        if _names_shared_data(item) and item.get_closest_marker("data") is None:
            item.add_marker(pytest.mark.data)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    """In CI mode a data test that skips (its data absent) is reported as a failure."""
    outcome = yield
    rep = outcome.get_result()
    if rep.skipped and item.get_closest_marker("data") is not None and data_required():
        reason = rep.longrepr[2] if isinstance(rep.longrepr, tuple) else str(rep.longrepr)
        rep.outcome = "failed"
        rep.longrepr = (f"data test skipped although data tests are required "
                        f"(EIFSLAM_REQUIRE_DATA=1 or {DATASETS} exists): {reason}")
