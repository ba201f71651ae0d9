"""The two kinds of mistake a user can fix, reported as one line with exit code 2."""

from __future__ import annotations


class ConfigError(ValueError):
    """A configuration value is missing, unknown, of the wrong type or out of range."""


class UserError(Exception):
    """A mistake the user can fix (a bad file, a bad parameter): one line, exit code 2."""
