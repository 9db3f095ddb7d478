"""Exceptions of the service package, one family per job (in the manner of BlueOS components)."""

from __future__ import annotations


class NetposeError(Exception):
    """Base of every error netpose raises on purpose."""


class ConfigError(NetposeError):
    """A configuration value is missing, unknown or invalid; `key` names it (e.g. 'camera.url')."""

    def __init__(self, key: str, problem: str) -> None:
        super().__init__(f"{key}: {problem}")
        self.key = key
        self.problem = problem


class SettingsLockedError(NetposeError):
    """A change from the web page that must wait: the vehicle is armed."""


class CalibrationError(NetposeError):
    """A camera calibration file cannot be read or describes an impossible camera."""


class EstimatorInputError(NetposeError):
    """The estimator was handed a frame it cannot use (wrong shape, dtype or size)."""
