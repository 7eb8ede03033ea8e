"""The one error a bad configuration raises (also importable from fluxdrive.core.machine)."""

from __future__ import annotations


class ConfigError(ValueError):
    """A configuration file or value is invalid; the message names the file, key and rule."""
