"""Seed statistics for the reports: mean ± std, and differences with a 95% t-interval.

The paper reports one training run per variant. We train S seeds and ask, for every difference
the paper claims, whether the seed-to-seed spread lets the data decide it: the mean difference
(paired by seed where both sides have the seed) with a 95% confidence interval from Student's t
distribution, and a verdict in words.

A verdict needs at least :data:`MIN_SEEDS` seeds on each side and an interval of nonzero width.
Why: the reported metrics are fractions of a finite test set (1/740 of an instance on the cpu
preset), so two seeds can easily differ by exactly the same count on both variants; their paired
differences are then identical, the sample std is 0, and Student's interval collapses to a point
that excludes 0 however small the difference. With two seeds the std also rests on a single
degree of freedom. The interval is still printed in those cases; only the verdict stays
"not resolved".
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np
from scipy import stats as sps

SUPPORTED = "supported"
CONTRADICTED = "contradicted"
UNRESOLVED = "not resolved at this size"

MIN_SEEDS = 3
"""Fewest seeds (paired: seeds both sides have) on which a claim gets a verdict."""


class MeanStd(NamedTuple):
    """Mean and sample standard deviation (ddof = 1; NaN for one value) of n values."""

    mean: float
    std: float
    n: int


def mean_std(values: Sequence[float]) -> MeanStd:
    """Mean and sample std of the finite ``values``; (NaN, NaN, 0) when there are none."""
    v = np.asarray([x for x in values if x is not None and np.isfinite(x)], dtype=float)
    if v.size == 0:
        return MeanStd(math.nan, math.nan, 0)
    std = float(np.std(v, ddof=1)) if v.size > 1 else math.nan
    return MeanStd(float(np.mean(v)), std, int(v.size))


def format_mean_std(ms: MeanStd, scale: float = 100.0, digits: int = 1) -> str:
    """``"76.0 ± 1.2"`` (values times ``scale``); ``"76.0"`` for one seed; ``"–"`` for none."""
    if ms.n == 0:
        return "–"
    if ms.n == 1 or not np.isfinite(ms.std):
        return f"{ms.mean * scale:.{digits}f}"
    return f"{ms.mean * scale:.{digits}f} ± {ms.std * scale:.{digits}f}"


class Difference(NamedTuple):
    """A measured difference ``a - b`` over seeds with its 95% confidence interval.

    Attributes:
        mean: mean difference (paired: mean of per-seed differences; else difference of means).
        low, high: the 95% confidence interval (NaN when it cannot be computed).
        n: seeds used (paired: seeds both sides have; unpaired: the smaller side).
        paired: whether the interval is a paired t-interval (else Welch's).
        verdict: :data:`SUPPORTED`, :data:`CONTRADICTED` or :data:`UNRESOLVED`.
        why: for :data:`UNRESOLVED`, the reason in words (too few seeds, an interval that
            contains 0, or one of zero width); "" otherwise.
    """

    mean: float
    low: float
    high: float
    n: int
    paired: bool
    verdict: str
    why: str = ""


def _t_interval(mean: float, se: float, dof: float, level: float) -> tuple[float, float]:
    if not (np.isfinite(se) and dof > 0):
        return math.nan, math.nan
    half = float(sps.t.ppf(0.5 + level / 2, dof)) * se
    return mean - half, mean + half


def difference(
    a: Mapping[int, float],
    b: Mapping[int, float],
    *,
    expect: int = 1,
    level: float = 0.95,
    min_seeds: int = MIN_SEEDS,
) -> Difference:
    """Difference ``a - b`` of a metric over seeds, its CI, and the verdict on a claim.

    Args:
        a: seed -> metric value of the side the claim favours (e.g. separate networks).
        b: seed -> metric value of the other side.
        expect: +1 if the claim says ``a`` is larger (accuracies), -1 if smaller (errors).
        level: confidence level.
        min_seeds: fewest seeds for a verdict (at least 2).

    Returns:
        Paired by seed when at least two seeds are on both sides (t with n - 1 degrees of
        freedom on the per-seed differences); otherwise Welch's interval when both sides have
        at least two seeds; otherwise no interval. The verdict is "supported" when the interval
        excludes 0 on the side the claim expects, "contradicted" when it excludes 0 on the other
        side, and "not resolved at this size" when it contains 0, has zero width (every paired
        difference equal: a spread below the metric's resolution, not a certainty), or rests on
        fewer than ``min_seeds`` seeds. The interval itself is computed from two seeds on.
    """
    if expect not in (1, -1):
        raise ValueError(f"expect must be +1 or -1, got {expect!r}")
    if min_seeds < 2:
        raise ValueError(f"min_seeds must be at least 2 (an interval needs two), got {min_seeds!r}")
    a = {s: float(v) for s, v in a.items() if v is not None and np.isfinite(v)}
    b = {s: float(v) for s, v in b.items() if v is not None and np.isfinite(v)}
    common = sorted(set(a) & set(b))
    if len(common) >= 2:
        d = np.array([a[s] - b[s] for s in common])
        mean = float(d.mean())
        se = float(d.std(ddof=1)) / math.sqrt(d.size)
        low, high = _t_interval(mean, se, d.size - 1, level)
        n, paired = d.size, True
    elif len(a) >= 2 and len(b) >= 2:
        va, vb = np.array(list(a.values())), np.array(list(b.values()))
        mean = float(va.mean() - vb.mean())
        qa, qb = va.var(ddof=1) / va.size, vb.var(ddof=1) / vb.size
        se = math.sqrt(qa + qb)
        denom = qa**2 / (va.size - 1) + qb**2 / (vb.size - 1)
        dof = (qa + qb) ** 2 / denom if denom > 0 else va.size + vb.size - 2
        low, high = _t_interval(mean, se, dof, level)
        n, paired = min(va.size, vb.size), False
    else:
        if a and b:
            mean = float(np.mean(list(a.values())) - np.mean(list(b.values())))
        else:
            mean = math.nan
        n = min(len(a), len(b))
        return Difference(
            mean, math.nan, math.nan, n, False, UNRESOLVED, f"{n} seed(s) of {min_seeds} needed"
        )
    # zero width up to float rounding (per-seed differences equal but for the last bits)
    if n < min_seeds:
        why = f"{n} seed(s) of {min_seeds} needed"
    elif not high - low > 1e-9 * max(1.0, abs(mean)):
        why = "every seed gives the same difference (below the test set's resolution)"
    else:
        why = ""
    result = verdict(low, high, expect) if not why else UNRESOLVED
    if result == UNRESOLVED and not why:
        why = "the interval contains 0"
    return Difference(mean, low, high, n, paired, result, why)


def verdict(low: float, high: float, expect: int = 1) -> str:
    """Verdict on a claim from a confidence interval of ``a - b`` (see :func:`difference`)."""
    if not (np.isfinite(low) and np.isfinite(high)):
        return UNRESOLVED
    if low > 0:
        return SUPPORTED if expect > 0 else CONTRADICTED
    if high < 0:
        return SUPPORTED if expect < 0 else CONTRADICTED
    return UNRESOLVED
