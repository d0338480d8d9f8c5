"""Errors that reach the user as one clear line.

Every failure that is the user's to fix (a bad file, a bad option, a cloud the method cannot use) raises a
subclass of :class:`GridPullError`. The command line prints ``error: <message>`` and exits non-zero without a
traceback; library users catch the class they care about.
"""

from __future__ import annotations


class GridPullError(Exception):
    """Base class of every error meant for the user (message is one line, names the problem)."""

    exit_code = 2


class InputError(GridPullError, ValueError):
    """An input file or array cannot be used (missing, unreadable, wrong format, empty, degenerate)."""

    exit_code = 3


class ConfigError(GridPullError, ValueError):
    """A configuration value or option is invalid (caught before any work starts)."""

    exit_code = 2


class MissingDependencyError(GridPullError, ImportError):
    """An optional dependency needed for this feature is not installed."""

    exit_code = 4


class MemoryBudgetError(GridPullError):
    """A tile or solve would exceed the memory budget the user set."""

    exit_code = 5


class TileFailedError(GridPullError):
    """One or more tiles failed for a data reason (reported by name)."""

    exit_code = 6


class ClusterError(GridPullError):
    """The Dask cluster cannot run the job (no worker for too long, or workers that cannot see the job
    directory)."""

    exit_code = 7
