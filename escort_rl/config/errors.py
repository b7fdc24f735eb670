"""The error every bad configuration value raises."""


class ConfigError(ValueError):
    """A bad configuration value or key; the message names the key and the fix."""


class MissingExtra(ImportError):
    """An optional dependency is not installed; the message names the feature and the install command
    (``pip install escort-rl[EXTRA]``)."""


def first_line(err: BaseException) -> str:
    """The first line of ``err``'s message (its type's name when it has none), for a one-line error
    that quotes its cause."""
    return (str(err).strip().splitlines() or [type(err).__name__])[0]
