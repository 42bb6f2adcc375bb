"""Exceptions that the CLI turns into one-line messages and a non-zero exit.

Every message names the offending file, topic, key or name and says what is wrong,
so that a user can fix the input without reading a traceback.
"""

from __future__ import annotations


class FtcalError(Exception):
    """Base of every error the user can fix (bad input, bad params, bad model)."""


class ConfigError(FtcalError):
    """An invalid or missing value in params.yaml (the message names the key)."""


class RobotModelError(FtcalError):
    """A URDF that cannot be used, or a sensor/frame/link name that it does not have."""


class DataError(FtcalError):
    """A log or table that cannot be used (the message names the file and the problem)."""


class JobError(FtcalError):
    """An unexpected exception inside a job of `pipeline.core.parallel.forked_map` (a library's ValueError or
    RuntimeError on the data): the message names the job's file or name and the exception, and the file that
    holds its traceback (the terminal shows one line)."""
