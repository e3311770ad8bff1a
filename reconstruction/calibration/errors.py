"""Errors of the calibration command: one line each, saying what to do."""

from __future__ import annotations

from roadsurf.core.errors import RoadsurfError


class CalibrationError(RoadsurfError):
    """A calibration cannot be computed or is too poor to use (too few or unusable images,
    too large a reprojection error, a ground board that is not found)."""


class BoardSpecError(CalibrationError):
    """A ``--board`` specification cannot be parsed."""
