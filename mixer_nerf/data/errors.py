"""Exceptions raised by the dataset loaders. Every message names the offending file."""

from __future__ import annotations


class DatasetError(ValueError):
    """A dataset on disk is malformed: bad JSON, missing keys, wrong shapes, corrupt images..."""


class MissingFileError(DatasetError, FileNotFoundError):
    """A file the dataset format requires is absent (catchable as DatasetError or FileNotFoundError)."""
