"""The error every bad configuration value raises."""


class ConfigError(ValueError):
    """A bad configuration value or key; the message names the key and the fix."""


class MissingExtra(ImportError):
    """An optional dependency is not installed; the message names the feature and the install command
    (``pip install escort-rl[EXTRA]``)."""
