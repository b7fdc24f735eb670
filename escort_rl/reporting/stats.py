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


def merge_importance(records) -> dict:
    """The importance-weight diagnostics of several cells (each a filter's ``importance_diagnostics()``
    or a dict of per-seed lists, or ``None``) as one: per-seed lists concatenated, ``min_ess_fraction``
    the minimum, ``count`` the sum, other scalars averaged with the cells' ``count`` as weights.

    Examples:
        >>> merge_importance([{"mean_ess_fraction": 0.25, "min_ess_fraction": 0.1, "count": 1},
        ...                   {"mean_ess_fraction": 0.5, "min_ess_fraction": 0.3, "count": 3}])
        {'count': 4, 'mean_ess_fraction': 0.4375, 'min_ess_fraction': 0.1}
    """
    records = [r or {} for r in records]
    merged: dict = {}
    for key in sorted({k for r in records for k in r}):
        values = [r[key] for r in records if key in r]
        if isinstance(values[0], list):
            merged[key] = [v for vs in values for v in vs]
        elif key == "min_ess_fraction":
            merged[key] = min(values)
        elif key == "count":
            merged[key] = sum(values)
        else:
            counts = [r.get("count", 1) for r in records if key in r]
            merged[key] = sum(v * c for v, c in zip(values, counts)) / max(sum(counts), 1)
    return merged


def format_importance(record: dict | None) -> str:
    """One cell of text for :func:`merge_importance`'s record: the ESS/N of the importance weights (its
    minimum, the share of tempered beliefs and the mean tempering exponent β where there are any), or
    ``"—"`` for a filter that forms none.

    Examples:
        >>> format_importance({"mean_ess_fraction": 0.4, "min_ess_fraction": 0.1, "tempered_fraction": 0.5,
        ...                    "mean_beta": 0.8, "count": 3})
        'ESS/N 0.400 (min 0.100), tempered 0.50, β 0.800'
        >>> format_importance({"ess_fraction": [0.25, 0.35]})
        'ESS/N 0.3000'
    """
    record = record or {}
    if "mean_ess_fraction" in record:
        return (f"ESS/N {record['mean_ess_fraction']:.3f} (min {record['min_ess_fraction']:.3f}), "
                f"tempered {record['tempered_fraction']:.2f}, β {record['mean_beta']:.3f}")
    if "ess_fraction" in record:
        return f"ESS/N {mean_se(record['ess_fraction'])[0]:.4f}"
    return "—"
