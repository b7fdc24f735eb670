"""The accuracy–cost front: pure functions on points ``(seconds, error)``, lower is better on both.

Example:
    >>> pts = [("a", 1.0, 5.0), ("b", 2.0, 3.0), ("c", 3.0, 4.0), ("d", 4.0, 1.0)]
    >>> [p[0] for p in pareto_front(pts)]
    ['a', 'b', 'd']
    >>> best_at_budgets(pts, [0.5, 2.5, 10.0])
    [None, ('b', 2.0, 3.0), ('d', 4.0, 1.0)]
"""

from __future__ import annotations

import math


def pareto_front(points):
    """The points no other point dominates, in order of cost. A point ``(label, cost, error, ...)``
    dominates another when its cost and its error are both ≤ and one of them is <. Points with a NaN
    cost or error (a diverged filter) are never on the front."""
    finite = [p for p in points if not (math.isnan(p[1]) or math.isnan(p[2]))]
    front = [p for p in finite
             if not any(q[1] <= p[1] and q[2] <= p[2] and (q[1] < p[1] or q[2] < p[2]) for q in finite)]
    return sorted(front, key=lambda p: (p[1], p[2]))


def best_at_budgets(points, budgets):
    """For each budget, the point of lowest error among those that cost at most that budget (the
    cheaper one on a tie), or ``None`` when none fits."""
    out = []
    for b in budgets:
        fits = [p for p in pareto_front(points) if p[1] <= b]
        out.append(min(fits, key=lambda p: (p[2], p[1])) if fits else None)
    return out
