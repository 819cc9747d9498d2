"""The statistics of a study: intervals, probability of improvement, censored steps to a threshold.

Intervals are rliable's stratified-bootstrap percentile intervals, computed here in one vectorised pass over
rliable's own draws (the same resamples, so the same numbers; a test compares the two); steps to a
threshold treat runs that never reached it as censored.

rliable (Agarwal et al. 2021) gives the interquartile mean, the stratified-bootstrap confidence intervals,
the probability of improvement and performance profiles. Steps to a threshold is a time-to-event measure:
a run that never reached the threshold needed more than its budget, so its value is censored; the median
over runs is then bounded (:func:`censored_median`), and the probability of improvement ranks a run that
never reached the threshold below every run that did. A maximum over a run's test evaluations is never a
result here: a run's result is its final evaluation (or the policy its own selection kept).

Every interval is computed with a fixed random state (``seed``), so a report reproduces its intervals.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "MIN_RUNS_FOR_VERDICT",
    "Interval",
    "censored_median",
    "comparable_steps",
    "iqm",
    "iqm_interval",
    "mean_interval",
    "paired_difference",
    "performance_profile",
    "probability_of_improvement",
    "steps_scores",
    "threshold_key",
    "verdict",
]


@dataclass(frozen=True)
class Interval:
    """A point estimate with its confidence interval (``low``, ``high``) and the number of runs behind it."""

    value: float
    low: float
    high: float
    n: int

    def text(self, fmt: str = "{:.2f}") -> str:
        """``"-10.07 [-10.16, -10.05]"``; ``"—"`` for no runs."""
        if self.n == 0 or not math.isfinite(self.value):
            return "—"
        return f"{fmt.format(self.value)} [{fmt.format(self.low)}, {fmt.format(self.high)}]"

    def as_dict(self) -> dict[str, Any]:
        """The interval as plain data (for records)."""
        return {"value": self.value, "low": self.low, "high": self.high, "n": self.n}


def threshold_key(threshold: float) -> str:
    """The key of a threshold in records and reports (``-11.0`` -> ``"-11"``)."""
    return f"{float(threshold):g}"


def _resamples(sizes: Sequence[int], reps: int, seed: int) -> list[np.ndarray]:
    """The indices of ``reps`` stratified-bootstrap resamples of arrays of ``sizes`` runs: one ``(reps, n)`` array each.

    They are rliable's draws, in its order: NumPy's global generator seeded with ``seed`` (rliable's
    ``StratifiedBootstrap`` draws there; the ``random_state`` it is given reaches arch only), one
    ``choice(n, (n, 1))`` per array and resample. The caller's global state is put back afterwards.
    """
    saved = np.random.get_state()
    np.random.seed(seed)
    try:
        if len(set(sizes)) == 1:  # consecutive draws of one bound are one draw of their total size
            n, k = int(sizes[0]), len(sizes)
            draws = np.random.choice(n, (reps, k, n), replace=True)  # resample r: array 0's n, array 1's n, ...
            return [draws[:, j, :] for j in range(k)]
        out = [np.empty((reps, int(n)), dtype=np.int64) for n in sizes]
        for r in range(reps):
            for indices, n in zip(out, sizes):
                indices[r] = np.random.choice(int(n), (int(n), 1), replace=True)[:, 0]
        return out
    finally:
        np.random.set_state(saved)


def _percentile_interval(results: np.ndarray, confidence: float) -> tuple[float, float]:
    """The percentile interval of bootstrap ``results`` (arch's ``conf_int(method="percentile")``)."""
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"a confidence level must lie strictly between 0 and 1, got {confidence}")
    alpha = (1.0 - confidence) / 2
    low, high = np.percentile(results, [100 * alpha, 100 * (1.0 - alpha)])
    return float(low), float(high)


def _trimmed_means(samples: np.ndarray) -> np.ndarray:
    """The interquartile mean of each row (scipy's ``trim_mean(row, 0.25)``, row by row, in one call)."""
    n = samples.shape[1]
    cut = int(0.25 * n)
    kept = np.partition(samples, (cut, n - cut - 1), axis=1)[:, cut : n - cut]
    return np.mean(kept, axis=1)


def _improvements(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """P(X > Y), ties counted half, for each row pair of ``x`` ``(R, n)`` and ``y`` ``(R, m)``: Mann-Whitney's U / nm.

    Rows are compared in chunks of at most about ten million pairs, so that many runs need no large memory.
    """
    pairs = x.shape[1] * y.shape[1]
    chunk = max(1, 10_000_000 // pairs)
    out = np.empty(len(x))
    for start in range(0, len(x), chunk):
        bx, by = x[start : start + chunk, :, None], y[start : start + chunk, None, :]
        out[start : start + chunk] = ((bx > by).sum((1, 2)) + 0.5 * (bx == by).sum((1, 2))) / pairs
    return out


def iqm(values: Sequence[float]) -> float:
    """The interquartile mean (25 % trimmed at each end; rliable's aggregate_iqm, as :func:`iqm_interval`'s point)."""
    return float(_trimmed_means(np.asarray(values, dtype=float).reshape(1, -1))[0])


def _over_runs(
    values: Sequence[float], func: Callable[[np.ndarray], np.ndarray], confidence: float, reps: int, seed: int
) -> Interval:
    """``func`` (of runs along axis 1) over the runs' ``values`` with its bootstrap interval (one run: no width)."""
    x = np.array([float(v) for v in values])
    if not len(x) or np.isnan(x).any():  # no runs, or a run without a number: no estimate (as rliable gave)
        return Interval(math.nan, math.nan, math.nan, len(x))
    if len(x) == 1:
        return Interval(float(x[0]), float(x[0]), float(x[0]), 1)
    (indices,) = _resamples([len(x)], reps, seed)
    low, high = _percentile_interval(func(x[indices]), confidence)
    return Interval(float(func(x[None, :])[0]), low, high, len(x))


def iqm_interval(values: Sequence[float], confidence: float = 0.95, reps: int = 10_000, seed: int = 0) -> Interval:
    """The IQM over runs with its stratified-bootstrap interval (a point without width for one run)."""
    return _over_runs(values, _trimmed_means, confidence, reps, seed)


def mean_interval(values: Sequence[float], confidence: float = 0.95, reps: int = 10_000, seed: int = 0) -> Interval:
    """The mean over runs with its bootstrap interval."""
    return _over_runs(values, lambda s: np.mean(s, axis=1), confidence, reps, seed)


def probability_of_improvement(
    better: Sequence[float], than: Sequence[float], confidence: float = 0.95, reps: int = 10_000, seed: int = 0
) -> Interval:
    """P(a run of ``better`` scores higher than a run of ``than``), ties counted half (rliable), with its interval.

    Scores may hold ``-inf`` (a censored run ranked below every finite one, e.g. :func:`steps_scores`).
    """
    x = np.asarray(better, dtype=float)
    y = np.asarray(than, dtype=float)
    if len(x) == 0 or len(y) == 0:
        return Interval(math.nan, math.nan, math.nan, 0)
    if np.isnan(x).any() or np.isnan(y).any():  # a run without a number: no estimate (as rliable gave)
        return Interval(math.nan, math.nan, math.nan, min(len(x), len(y)))
    x, y = _ranked(x, y)
    ix, iy = _resamples([len(x), len(y)], reps, seed)
    low, high = _percentile_interval(_improvements(x[ix], y[iy]), confidence)
    return Interval(float(_improvements(x[None, :], y[None, :])[0]), low, high, min(len(x), len(y)))


def _ranked(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Finite stand-ins for infinite scores that keep every order (Mann-Whitney sees ranks only)."""
    both = np.concatenate([x, y])
    finite = both[np.isfinite(both)]
    low = (finite.min() if finite.size else 0.0) - 1.0
    high = (finite.max() if finite.size else 0.0) + 1.0
    fix = lambda a: np.where(np.isneginf(a), low, np.where(np.isposinf(a), high, a))
    return fix(x), fix(y)


def paired_difference(
    better: Mapping[int, float], than: Mapping[int, float], confidence: float = 0.95, reps: int = 10_000, seed: int = 0
) -> Interval:
    """The mean over the seeds both arms ran of ``better[seed] - than[seed]``, with its bootstrap interval."""
    common = sorted(set(better) & set(than))
    diffs = [float(better[s]) - float(than[s]) for s in common]
    return mean_interval(diffs, confidence, reps, seed)


def steps_scores(steps: Sequence[int | None]) -> list[float]:
    """Scores for ranking steps to a threshold: fewer steps score higher; a run that never reached it, ``-inf``."""
    return [-math.inf if s is None else -float(s) for s in steps]


def censored_median(steps: Sequence[int | None], budgets: Sequence[int]) -> dict[str, float | None]:
    """The median over runs of the steps to a threshold, where runs that never reached it are censored.

    ``steps[i]`` is ``None`` for a run that never reached it within ``budgets[i]`` steps: it needed more.
    Counting such runs at their budgets gives a lower bound on the median, at infinity an upper bound; where
    the two agree the median is measured (``median``), else it lies above the first (``above``) and at most
    at the second where that is finite (``at_most``).
    """
    out: dict[str, float | None] = {"median": None, "above": None, "at_most": None}
    if not steps:
        return out
    reached = [float(s) for s in steps if s is not None]
    censored = [float(b) for s, b in zip(steps, budgets) if s is None]
    low = float(np.median(reached + censored))
    high = float(np.median(reached + [math.inf] * len(censored)))
    if low == high:
        out["median"] = low
    else:
        out["above"] = low
        out["at_most"] = high if math.isfinite(high) else None
    return out


def median_text(median: Mapping[str, float | None]) -> str:
    """``"55,000"``, ``"> 50,000 and <= 60,000"`` or ``"> 60,000"`` (see :func:`censored_median`)."""
    if median.get("median") is not None:
        return f"{median['median']:,.0f}"
    if median.get("above") is None:
        return "—"
    text = f"> {median['above']:,.0f}"
    return text if median.get("at_most") is None else f"{text} and <= {median['at_most']:,.0f}"


#: the fewest runs per arm for a verdict other than inconclusive: with fewer, perfectly separated arms give
#: a bootstrap interval of [1, 1] (every resample separates them too), which is no evidence
MIN_RUNS_FOR_VERDICT = 5


def verdict(poi: Interval, runs: tuple[int, int] | None = None) -> str:
    """A hypothesis "better beats than" judged on the probability of improvement's interval.

    ``supported`` where the whole interval lies above 0.5, ``not supported`` where it lies below 0.5,
    ``inconclusive`` where it contains 0.5, where there are no runs, or where either arm has fewer than
    :data:`MIN_RUNS_FOR_VERDICT` runs (``runs``: the two arms' numbers of runs).
    """
    if poi.n == 0 or not math.isfinite(poi.low):
        return "inconclusive (no comparable runs)"
    if runs is not None and min(runs) < MIN_RUNS_FOR_VERDICT:
        return f"inconclusive (fewer than {MIN_RUNS_FOR_VERDICT} runs per arm)"
    if poi.low > 0.5:
        return "supported"
    if poi.high < 0.5:
        return "not supported"
    return "inconclusive"


def performance_profile(scores: Mapping[str, Sequence[float]], taus: Sequence[float]) -> dict[str, list[float]]:
    """For each arm, the fraction of its runs scoring above each ``tau`` (rliable's run-score distribution)."""
    from rliable import library

    arrays = {k: np.asarray(v, dtype=float).reshape(-1, 1) for k, v in scores.items() if len(v)}
    if not arrays:
        return {}
    saved = np.random.get_state()  # its bootstrap (of intervals not used here) draws from the global generator
    np.random.seed(0)
    try:
        profiles, _ = library.create_performance_profile(arrays, np.asarray(taus, dtype=float), reps=100)
    finally:
        np.random.set_state(saved)
    return {k: [float(x) for x in v] for k, v in profiles.items()}


def comparable_steps(
    steps_a: Sequence[int | None], budgets_a: Sequence[int], steps_b: Sequence[int | None], budgets_b: Sequence[int]
) -> bool:
    """Whether ranking two arms' runs by their steps to a threshold is sound.

    It is where every censored run's budget reaches past every measured step of the other arm (else a run
    stopped early would rank below one that reached the threshold later).
    """
    reached_a = [s for s in steps_a if s is not None]
    reached_b = [s for s in steps_b if s is not None]
    for steps, budgets, other in ((steps_a, budgets_a, reached_b), (steps_b, budgets_b, reached_a)):
        for s, b in zip(steps, budgets):
            if s is None and other and b < max(other):
                return False
    return True
