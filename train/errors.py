"""Errors of the training stage. All derive from :class:`crater_core.errors.ContractError` (the core's
bad-input base; ``train`` never imports the CLI layer), so the CLI prints one ``error: ...`` line
naming the bad input and exits with status 2."""

from __future__ import annotations

from crater_core.errors import ContractError


class TrainError(ContractError):
    """Base class of bad-input errors raised by ``train/``."""


class DatasetError(TrainError):
    """A manifest row, an EXR it points to, or the resulting class/split layout is unusable."""


class RealDataLeakError(TrainError):
    """A real (test) image was about to enter the training or validation data."""


class RealSetError(TrainError):
    """The real test set cannot be built: missing/corrupt product, bad labels file, unknown crater."""


class ModelError(TrainError):
    """A saved model is missing, corrupt or inconsistent with the configuration."""
