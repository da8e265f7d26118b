"""Named exceptions of genreg_core, and its one warning. Every bad input raises one of these with a one-line
message."""

from __future__ import annotations


class GenRegError(Exception):
    """Base class of every error raised on purpose by genreg_core."""


class InvalidPointCloudError(GenRegError, ValueError):
    """A cloud is not a real-valued (N, 3) array."""


class TooFewPointsError(GenRegError, ValueError):
    """A cloud has fewer usable (finite) points than registration needs."""


class NonFinitePointsError(TooFewPointsError):
    """A cloud holds only NaN/Inf points."""


class CheckpointError(GenRegError, RuntimeError):
    """A checkpoint is missing, corrupt, or built for another configuration (e.g. another N)."""


class DataNotFoundError(GenRegError, FileNotFoundError):
    """The dataset folder (setting `data_root`, env `GENREG_DATA`) or a file in it does not exist."""


class ConfigError(GenRegError, ValueError):
    """A configuration value is out of range or of the wrong type."""


class UncalibratedWarning(UserWarning):
    """A registrar's confidence is uncalibrated: its checkpoint has no confidence calibration, or none for the
    refinement in use (`genreg_core.result`). Warned once when the registrar is built or its refinement
    changes; filter it (`warnings.filterwarnings("ignore", category=UncalibratedWarning)`) where that is meant."""
