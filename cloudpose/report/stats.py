"""Seed statistics for the reports: mean ± std, differences with a 95% interval, verdicts.

The paper reports one training run per variant. We train S seeds and ask, for every difference
the paper claims, what the data say about it: the mean difference (paired by seed) with a 95%
interval, and a verdict with a name a reader can act on (:func:`classify`).

The interval must carry both sources of chance in a reported number: which seed trained the
network, and which test instances it was scored on. With the per-instance results of every run
(:func:`bootstrap_difference`) it is a two-level percentile bootstrap: each replicate draws
the seeds with replacement, then the test instances with replacement (the same draw for both
sides, which share the test set), and recomputes the metric of every drawn run on the drawn
instances. Without them it is Student's t over the per-seed differences (:func:`difference`).

Either way the interval is never narrower than a floor from the pooled spread: the t interval of
n paired seed differences that scatter as much as the differences of every variant pair of the
sweep do on that metric (:func:`pooled_sd`, :func:`floor_halfwidth`). Why: three seeds can agree by chance. On the cpu preset
the three paired differences of one pair agreed to 0.005 pp of ADS AUC while the median spread
across the 78 variant pairs was 0.26 pp; a rule that trusted the pair's own spread reported
luck as evidence. The bootstrap over three seeds has the same weakness (it cannot see spread the
three seeds do not show), which the floor covers too.

A verdict needs at least :data:`MIN_SEEDS` seeds on each side. With fewer, the interval is still
printed; only the verdict stays "not resolved".
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple

import numpy as np
from scipy import stats as sps

from cloudpose.metrics.summaries import voc_ap_auc

SUPPORTED = "supported"
"""The interval excludes 0 on the claimed side and holds the paper's size (or there is none)."""
CONTRADICTED = "contradicted"
"""The interval excludes 0 on the other side."""
SMALLER = "smaller than the paper's"
"""The interval lies below the paper's own difference (it may still exclude 0: the direction
is then supported, the size is not)."""
LARGER = "larger than the paper's"
"""The interval excludes 0 on the claimed side and lies above the paper's own difference."""
EQUIVALENT = "equivalent"
"""The interval contains 0 and lies inside +-margin: no difference a reader should act on."""
UNRESOLVED = "not resolved"
"""None of the above: the data cannot decide at this number of seeds (see ``why``)."""

OUTCOMES = (SUPPORTED, LARGER, SMALLER, EQUIVALENT, CONTRADICTED, UNRESOLVED)

AUC_MARGIN = 0.01
"""Equivalence margin of an AUC metric (1 pp): four times the pooled seed spread of ADS AUC on
the cpu preset (0.26 pp) and the smallest difference Table I of the paper separates methods by."""
THRESHOLD_MARGIN = 0.02
"""Equivalence margin of a threshold metric (share under 10 deg, 1 cm, ...; 2 pp): its paired
seed spread is 1.2-1.7 pp on the cpu preset, and the paper's one-run figures move by more."""


def margin_for(metric: str) -> float:
    """The equivalence margin (a fraction) of a metric name such as ``ads_auc``."""
    return AUC_MARGIN if metric.endswith("_auc") else THRESHOLD_MARGIN


MIN_SEEDS = 3
"""Fewest seeds (paired: seeds both sides have) on which a claim gets a verdict."""

MAX_SEEDS = 10
"""The most seeds a sweep trains of a variant to decide a claim (``--max-seeds``)."""


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
    """A measured difference ``a - b`` over seeds with its 95% interval and verdict.

    Attributes:
        mean: mean difference (paired: mean of per-seed differences; else difference of means).
        low, high: the 95% interval (NaN when it cannot be computed).
        n: seeds used (paired: seeds both sides have; unpaired: the smaller side).
        paired: whether the seeds are paired.
        verdict: one of :data:`OUTCOMES` (see :func:`classify`).
        why: the reason for the verdict in words where it needs one ("" otherwise).
        method: how the interval was made: ``bootstrap`` (seeds x instances), ``t`` (over
            seeds), ``welch``; ``+floor`` when the pooled-spread floor widened it.
    """

    mean: float
    low: float
    high: float
    n: int
    paired: bool
    verdict: str
    why: str = ""
    method: str = "t"


def _t_interval(mean: float, se: float, dof: float, level: float) -> tuple[float, float]:
    if not (np.isfinite(se) and dof > 0):
        return math.nan, math.nan
    half = float(sps.t.ppf(0.5 + level / 2, dof)) * se
    return mean - half, mean + half


class Pooled(NamedTuple):
    """The seed-to-seed spread of a paired difference of one metric, pooled across variants.

    Attributes:
        sd: sqrt of the mean, over all pairs of variants with two or more common seeds, of the
            sample variance of their per-seed differences (a fraction).
        dof: degrees of freedom credited to it: the sum over variants of (seeds - 1), the
            number of independent seed deviations the pairs are made of.
    """

    sd: float
    dof: int


NO_POOL = Pooled(math.nan, 0)


def pooled_sd(series: Sequence[Mapping[int, float]]) -> Pooled:
    """Pool the spread of paired seed differences of a metric across all variant pairs.

    Args:
        series: per variant, seed -> metric value (one metric, one prefix).

    Returns:
        :class:`Pooled`; :data:`NO_POOL` when no pair has two common seeds. Every variant of
        a sweep trains from the same seeds on the same data, so the spread of any pair's
        differences estimates how much a difference moves from seed to seed; pooled over the
        78 pairs of 13 variants it rests on 26 seed deviations instead of the 2 of one pair.
    """
    series = [{s: v for s, v in x.items() if np.isfinite(v)} for x in series]
    variances, used = [], set()
    for i in range(len(series)):
        for j in range(i + 1, len(series)):
            common = sorted(set(series[i]) & set(series[j]))
            if len(common) >= 2:
                d = [series[i][s] - series[j][s] for s in common]
                variances.append(float(np.var(d, ddof=1)))
                used |= {i, j}
    if not variances:
        return NO_POOL
    dof = sum(len(series[i]) - 1 for i in used)
    return Pooled(math.sqrt(float(np.mean(variances))), dof)


def floor_halfwidth(pooled: Pooled, n: int, level: float = 0.95) -> float:
    """Half-width of the t interval (``pooled.dof`` degrees of freedom) of a mean of ``n``
    paired differences with standard deviation ``pooled.sd``; 0 without a pooled estimate or
    with fewer than 2 seeds."""
    if not (pooled.dof > 0 and np.isfinite(pooled.sd) and n >= 2):
        return 0.0
    return float(sps.t.ppf(0.5 + level / 2, pooled.dof)) * pooled.sd / math.sqrt(n)


def _widen(mean: float, low: float, high: float, half: float) -> tuple[float, float, bool]:
    """``[low, high]`` widened to at least ``mean +- half``; whether it was."""
    new_low, new_high = min(low, mean - half), max(high, mean + half)
    return new_low, new_high, (new_low < low or new_high > high)


def classify(
    low: float,
    high: float,
    expect: int = 1,
    paper: float = math.nan,
    margin: float = math.nan,
) -> tuple[str, str]:
    """The verdict on a claim from the interval ``[low, high]`` of ``favoured - other``.

    Args:
        low, high: the interval, in the metric's unit (fractions for shares and AUCs).
        expect: +1 if the claim says the favoured side is larger, -1 if smaller (errors).
        paper: the paper's own difference in the same unit (NaN: none).
        margin: the equivalence margin, same unit (NaN: no equivalence test).

    Returns:
        (verdict, why). Read along the claim's direction (a larger difference favours the
        claim), with ``p`` the paper's difference when it is in the claim's direction (> 0):
        :data:`CONTRADICTED` when the interval is below 0; when it is above 0,
        :data:`SMALLER` if it is also below ``p``, :data:`LARGER` if above ``p``, else
        :data:`SUPPORTED`; when it contains 0, :data:`EQUIVALENT` if it lies inside
        ``+-margin``, :data:`SMALLER` if it lies below ``p``, else :data:`UNRESOLVED`.
    """
    if expect not in (1, -1):
        raise ValueError(f"expect must be +1 or -1, got {expect!r}")
    if not (np.isfinite(low) and np.isfinite(high)):
        return UNRESOLVED, "no interval"
    lo, hi = sorted((expect * low, expect * high))
    p = expect * paper if np.isfinite(paper) else math.nan
    has_size = np.isfinite(p) and p > 0
    pp = f"{100 * p:+.1f} pp" if np.isfinite(p) else ""
    if hi < 0:
        return CONTRADICTED, ""
    if lo > 0:
        if has_size and hi < p:
            return SMALLER, f"direction supported; the paper's {pp} is above the interval"
        if has_size and lo > p:
            return LARGER, f"the paper's {pp} is below the interval"
        if np.isfinite(p) and p <= 0:
            return SUPPORTED, f"the paper's own figure is {pp}"
        return SUPPORTED, ""
    if np.isfinite(margin) and -margin < lo and hi < margin:
        note = f"; the paper's {pp} is outside" if has_size and hi < p else ""
        return EQUIVALENT, f"inside +-{100 * margin:g} pp{note}"
    if has_size and hi < p:
        return SMALLER, f"contains 0; the paper's {pp} is above the interval"
    if has_size:
        return UNRESOLVED, f"the interval contains 0 and the paper's {pp}"
    return UNRESOLVED, "the interval contains 0" + (
        f" and is wider than +-{100 * margin:g} pp" if np.isfinite(margin) else ""
    )


def difference(
    a: Mapping[int, float],
    b: Mapping[int, float],
    *,
    expect: int = 1,
    level: float = 0.95,
    min_seeds: int = MIN_SEEDS,
    paper: float = math.nan,
    margin: float = math.nan,
    floor: Pooled = NO_POOL,
) -> Difference:
    """Difference ``a - b`` of a metric over seeds, its interval, and the verdict on a claim.

    Args:
        a: seed -> metric value of the side the claim favours (e.g. separate networks).
        b: seed -> metric value of the other side.
        expect: +1 if the claim says ``a`` is larger (accuracies), -1 if smaller (errors).
        level: confidence level.
        min_seeds: fewest seeds for a verdict (at least 2).
        paper, margin: the paper's difference and the equivalence margin (:func:`classify`).
        floor: the metric's pooled seed spread (:func:`pooled_sd`); the interval is at least
            :func:`floor_halfwidth` either side of the mean.

    Returns:
        Paired by seed when at least two seeds are on both sides (t with n - 1 degrees of
        freedom on the per-seed differences); otherwise Welch's interval when both sides have
        at least two seeds; otherwise no interval. "not resolved" with fewer than
        ``min_seeds`` seeds, or when the interval has zero width (every paired difference
        equal and no floor: a spread below the metric's resolution, not a certainty).
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
        n, paired, method = d.size, True, "t"
    elif len(a) >= 2 and len(b) >= 2:
        va, vb = np.array(list(a.values())), np.array(list(b.values()))
        mean = float(va.mean() - vb.mean())
        qa, qb = va.var(ddof=1) / va.size, vb.var(ddof=1) / vb.size
        se = math.sqrt(qa + qb)
        denom = qa**2 / (va.size - 1) + qb**2 / (vb.size - 1)
        dof = (qa + qb) ** 2 / denom if denom > 0 else va.size + vb.size - 2
        low, high = _t_interval(mean, se, dof, level)
        n, paired, method = min(va.size, vb.size), False, "welch"
    else:
        if a and b:
            mean = float(np.mean(list(a.values())) - np.mean(list(b.values())))
        else:
            mean = math.nan
        n = min(len(a), len(b))
        return Difference(
            mean, math.nan, math.nan, n, False, UNRESOLVED, f"{n} seed(s) of {min_seeds} needed"
        )
    return _judged(
        mean,
        low,
        high,
        n,
        paired,
        method,
        floor=floor,
        level=level,
        expect=expect,
        min_seeds=min_seeds,
        paper=paper,
        margin=margin,
    )


def _judged(
    mean, low, high, n, paired, method, *, floor, level, expect, min_seeds, paper, margin
) -> Difference:
    """The interval widened to the pooled floor, and the verdict on it."""
    low, high, widened = _widen(mean, low, high, floor_halfwidth(floor, n, level))
    method += "+floor" if widened else ""
    if n < min_seeds:
        return Difference(
            mean, low, high, n, paired, UNRESOLVED, f"{n} seed(s) of {min_seeds} needed", method
        )
    # zero width up to float rounding (per-seed differences equal but for the last bits)
    if not high - low > 1e-9 * max(1.0, abs(mean)):
        why = "every seed gives the same difference (below the test set's resolution)"
        return Difference(mean, low, high, n, paired, UNRESOLVED, why, method)
    result, why = classify(low, high, expect, paper, margin)
    return Difference(mean, low, high, n, paired, result, why, method)


def seeds_to_decide(
    d: Difference,
    *,
    floor: Pooled = NO_POOL,
    cap: int = MAX_SEEDS,
    level: float = 0.95,
    expect: int = 1,
    paper: float = math.nan,
    margin: float = math.nan,
    min_seeds: int = MIN_SEEDS,
) -> int | None:
    """The fewest seeds at which the undecided difference ``d`` would get a verdict, if its mean
    stayed where it is; None when no count up to ``cap`` would.

    The projection keeps the mean and narrows each side of the interval as 1/sqrt(seeds), never
    below the pooled floor at that count (:func:`floor_halfwidth`), then asks :func:`classify`.
    It is optimistic where the test set's own chance makes much of the width (more seeds do
    not shrink that part), so it may ask for seeds that then do not decide; what it saves are
    the claims that no number of seeds up to the cap could decide: a mean halfway between 0
    and the paper's size with a spread that keeps both inside, or an equivalence margin below
    the floor at the cap.

    Returns:
        ``d.n`` when ``d`` is decided; for fewer than ``min_seeds`` seeds, ``min_seeds`` (no
        interval to project from yet, capped at ``cap``); else the count in ``(d.n, cap]`` or
        None.
    """
    if d.verdict != UNRESOLVED:
        return d.n
    if d.n < min_seeds:
        return min(min_seeds, cap) if cap > d.n else None
    if not (np.isfinite(d.low) and np.isfinite(d.high)):
        return None
    if not d.high - d.low > 1e-9 * max(1.0, abs(d.mean)):
        return None  # every seed gives the same difference: more seeds give it again
    for n in range(d.n + 1, cap + 1):
        shrink = math.sqrt(d.n / n)
        low, high, _ = _widen(
            d.mean,
            d.mean - (d.mean - d.low) * shrink,
            d.mean + (d.high - d.mean) * shrink,
            floor_halfwidth(floor, n, level),
        )
        if classify(low, high, expect, paper, margin)[0] != UNRESOLVED:
            return n
    return None


def bootstrap_difference(
    a: Mapping[int, np.ndarray],
    b: Mapping[int, np.ndarray],
    stat: Callable[[np.ndarray], np.ndarray],
    *,
    expect: int = 1,
    level: float = 0.95,
    min_seeds: int = MIN_SEEDS,
    paper: float = math.nan,
    margin: float = math.nan,
    floor: Pooled = NO_POOL,
    replicates: int = 2000,
    seed: int = 0,
) -> Difference:
    """Difference ``stat(a) - stat(b)`` over seeds and test instances, two-level bootstrap.

    Args:
        a, b: seed -> (N,) per-instance values of one run (errors or distances), the same N
            test instances in the same order for every run.
        stat: the metric of a batch of instance draws, (R, N) -> (R,), e.g. the share below a
            threshold (:func:`share_below`) or the toolbox AUC (:func:`auc_of_rows`).
        replicates: bootstrap replicates.
        seed: seed of the bootstrap's own random draws (the report is deterministic).
        Others: as :func:`difference`.

    Returns:
        The mean of the per-seed differences on the full test set, and the percentile interval
        of the replicates, each of which draws the paired seeds with replacement and the test
        instances with replacement (one draw shared by every run of the replicate), widened to
        the pooled floor. Unpaired seeds fall back to :func:`difference` on the per-run metrics.
    """
    if expect not in (1, -1):
        raise ValueError(f"expect must be +1 or -1, got {expect!r}")
    common = sorted(set(a) & set(b))
    if len(common) < 2:
        va = {s: float(stat(np.asarray(v, float)[None])[0]) for s, v in a.items()}
        vb = {s: float(stat(np.asarray(v, float)[None])[0]) for s, v in b.items()}
        return difference(
            va,
            vb,
            expect=expect,
            level=level,
            min_seeds=min_seeds,
            paper=paper,
            margin=margin,
            floor=floor,
        )
    xa = np.stack([np.asarray(a[s], float) for s in common])  # (S, N)
    xb = np.stack([np.asarray(b[s], float) for s in common])
    if xa.shape != xb.shape or xa.ndim != 2:
        raise ValueError(
            f"per-instance values: expected equal (N,) arrays, got {xa.shape}, {xb.shape}"
        )
    n_seeds, n_inst = xa.shape
    full = stat(xa) - stat(xb)  # (S,)
    mean = float(full.mean())
    rng = np.random.default_rng(seed)
    draws = np.empty(replicates)
    for r in range(replicates):
        seeds = rng.integers(0, n_seeds, n_seeds)
        inst = rng.integers(0, n_inst, n_inst)
        draws[r] = float(np.mean(stat(xa[seeds][:, inst]) - stat(xb[seeds][:, inst])))
    low, high = (float(q) for q in np.quantile(draws, [0.5 - level / 2, 0.5 + level / 2]))
    return _judged(
        mean,
        low,
        high,
        n_seeds,
        True,
        "bootstrap",
        floor=floor,
        level=level,
        expect=expect,
        min_seeds=min_seeds,
        paper=paper,
        margin=margin,
    )


def share_below(threshold: float) -> Callable[[np.ndarray], np.ndarray]:
    """``stat`` for :func:`bootstrap_difference`: the share of each row strictly below
    ``threshold`` (misses are ``inf``), as :func:`cloudpose.metrics.summaries.fraction_below`."""

    def stat(x: np.ndarray) -> np.ndarray:
        return np.mean(x < threshold, axis=-1)

    return stat


def auc_of_rows(x: np.ndarray) -> np.ndarray:
    """``stat`` for :func:`bootstrap_difference`: the toolbox AUC of each row, (R, N) -> (R,)."""
    return np.array([voc_ap_auc(row) for row in np.atleast_2d(x)])
