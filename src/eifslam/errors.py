"""Exceptions for bad input. Expected failures (too few matches, no baseline) are values,
not exceptions; see :mod:`eifslam.estimation.measurements`."""

from __future__ import annotations


class EifslamError(Exception):
    """Base class of every error eifslam raises on bad input; the CLI prints it in one line."""


class DatasetError(EifslamError):
    """A data set folder, image list or ground-truth file is missing or malformed."""


class CalibrationError(EifslamError):
    """A camera file is missing, malformed or physically impossible."""


class ImageError(EifslamError):
    """An image cannot be read or decoded."""


class ConfigError(EifslamError):
    """A configuration key is unknown or a value is out of range."""


class EstimatorError(EifslamError):
    """The estimator was asked something it cannot answer (unknown state, singular system)."""


class OutputError(EifslamError):
    """An output folder or file cannot be created or written."""


class SessionError(EifslamError):
    """A session file is not one this eifslam wrote (foreign, truncated, crafted or of
    another version)."""
