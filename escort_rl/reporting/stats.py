"""Mean ± standard error over seeds or episodes, and its one text form for every table."""

from __future__ import annotations

import math


def mean_se(values) -> tuple[float, float]:
    """The mean and the standard error of the mean (sample standard deviation / sqrt(n)) of
    ``values``, NaN entries left out.

    Returns ``(nan, nan)`` when nothing is left and a standard error of 0 for a single value.

    Examples:
        >>> mean_se([1.0, 2.0, 3.0])
        (2.0, 0.5773502691896257)
        >>> mean_se([float("nan"), 4.0])
        (4.0, 0.0)
    """
    v = [float(a) for a in values if not math.isnan(float(a))]
    if not v:
        return float("nan"), float("nan")
    m = sum(v) / len(v)
    if len(v) < 2:
        return m, 0.0
    return m, math.sqrt(sum((a - m) ** 2 for a in v) / (len(v) - 1) / len(v))


def format_mean_se(pair, digits: int = 3) -> str:
    """``"m ± se"`` with ``digits`` decimals; ``"—"`` for a missing (``None``) or NaN mean.

    Examples:
        >>> format_mean_se((0.12345, 0.01))
        '0.123 ± 0.010'
        >>> format_mean_se((float("nan"), float("nan")))
        '—'
    """
    m, se = pair
    return "—" if m is None or math.isnan(m) else f"{m:.{digits}f} ± {se:.{digits}f}"
