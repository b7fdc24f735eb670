"""The error every bad configuration value raises."""


class ConfigError(ValueError):
    """A bad configuration value or key; the message names the key and the fix."""
