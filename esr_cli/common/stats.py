"""Statistics over seeds that reviewers accept (after Agarwal et al. 2021, "Deep RL at the edge
of the statistical precipice"): the interquartile mean (IQM) with a stratified bootstrap
confidence interval, and the probability that one method improves on another.

The resampling is scipy's (`scipy.stats.bootstrap`, percentile intervals). Passing one sample
per task with `paired=False` resamples seeds within each task independently, which is the
stratified bootstrap: every resample keeps each task's number of seeds. All functions are
deterministic for a given `seed`.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

CONFIDENCE = 0.95
EQUIVALENCE_CONFIDENCE = 0.90  # two one-sided tests at 5% each
RESAMPLES = 2000
TRIM = 0.25  # the IQM drops the bottom and top quarter of all runs


def iqm(values, axis: int = -1) -> np.ndarray | float:
    """Interquartile mean: the mean of the middle 50% (scipy's 25% trimmed mean)."""
    from scipy import stats as sps  # about 1 s to import: only where a statistic is computed

    return sps.trim_mean(np.asarray(values, dtype=float), TRIM, axis=axis)


def _pooled_iqm(*samples, axis=-1):
    return iqm(np.concatenate(samples, axis=axis), axis=axis)


def _bootstrap_ci(statistic, samples: Sequence[np.ndarray], confidence: float, resamples: int,
                  seed: int) -> tuple[float, float]:
    """scipy's percentile bootstrap of `statistic(*samples, axis=-1)`, each sample resampled on
    its own. A sample of one value is held fixed: resampling it can only return it again, and
    scipy refuses samples of fewer than two values (a 10-seed run against a 1-seed baseline)."""
    varying = [i for i, s in enumerate(samples) if len(s) >= 2]

    def with_fixed(*drawn, axis=-1):
        batch = np.moveaxis(drawn[0], axis, -1).shape[:-1]
        full = list(samples)
        for i, d in zip(varying, drawn):
            full[i] = np.moveaxis(d, axis, -1)
        full = [f if i in varying else np.broadcast_to(f, batch + f.shape) for i, f in enumerate(full)]
        return statistic(*full, axis=-1)

    from scipy import stats as sps

    res = sps.bootstrap(tuple(samples[i] for i in varying), with_fixed, paired=False, vectorized=True,
                        confidence_level=confidence, n_resamples=resamples, method="percentile",
                        rng=np.random.default_rng(seed))
    return float(res.confidence_interval.low), float(res.confidence_interval.high)


def iqm_ci(samples: Sequence[Sequence[float]], confidence: float = CONFIDENCE, resamples: int = RESAMPLES,
           seed: int = 0) -> tuple[float, float, float] | None:
    """(IQM over all runs, low, high): a stratified bootstrap interval with one sample (the
    per-seed scores) per task. None when no task has two seeds (nothing to resample)."""
    samples = [np.asarray(s, dtype=float) for s in samples if len(s)]
    if not samples or max(len(s) for s in samples) < 2:
        return None
    point = float(_pooled_iqm(*samples))
    return (point, *_bootstrap_ci(_pooled_iqm, samples, confidence, resamples, seed))


def _improvement(x, y, axis=-1):
    """P(X > Y) + P(X = Y) / 2 over all pairs of a run of X and a run of Y (the Mann-Whitney
    U statistic of X divided by the number of pairs)."""
    x, y = np.moveaxis(np.asarray(x), axis, -1), np.moveaxis(np.asarray(y), axis, -1)
    diff = x[..., :, None] - y[..., None, :]
    return ((diff > 0) + 0.5 * (diff == 0)).mean(axis=(-2, -1))


def finite(values: Sequence[float]) -> np.ndarray:
    """The values that are numbers: a seed whose final score is NaN (no epoch in its final window
    logged the metric) has no score to rank, and counting it as a loss or a win would invent one."""
    values = np.asarray(values, dtype=float).ravel()
    return values[np.isfinite(values)]


def _two_sample(statistic, x, y, confidence: float, resamples: int, seed: int) -> tuple[float, float | None, float | None]:
    """(statistic(X, Y), low, high) over the seeds with a finite score, each side resampled on its
    own; (nan, None, None) when a side has none, no interval when both have one seed."""
    x, y = finite(x), finite(y)
    if not len(x) or not len(y):
        return float("nan"), None, None
    point = float(statistic(x, y))
    if max(len(x), len(y)) < 2:
        return point, None, None
    return (point, *_bootstrap_ci(statistic, [x, y], confidence, resamples, seed))


def probability_of_improvement(x: Sequence[float], y: Sequence[float], confidence: float = CONFIDENCE,
                               resamples: int = RESAMPLES, seed: int = 0) -> tuple[float, float | None, float | None]:
    """(P(X > Y), low, high): the probability that a run of X scores above a run of Y (ties
    count half), with a bootstrap interval that resamples each method's seeds separately
    (None, None when both have a single seed; a method with one seed is held fixed). Seeds
    without a finite score are left out; (nan, None, None) when a side has none."""
    return _two_sample(_improvement, x, y, confidence, resamples, seed)


def _mean_difference(x, y, axis=-1):
    return np.mean(x, axis=axis) - np.mean(y, axis=axis)


def mean_difference_ci(x: Sequence[float], y: Sequence[float], confidence: float = EQUIVALENCE_CONFIDENCE,
                       resamples: int = RESAMPLES, seed: int = 0) -> tuple[float, float | None, float | None]:
    """(mean(X) - mean(Y), low, high): a bootstrap interval resampling each side's seeds on its
    own (a one-seed side held fixed; None, None when both have one seed). At 90% it is the
    interval of the two one-sided tests of equivalence at the 5% level."""
    return _two_sample(_mean_difference, x, y, confidence, resamples, seed)


def describe(per_seed: Sequence[float]) -> dict:
    """Everything a table prints about one run's per-seed final scores: mean, standard error,
    IQM with its bootstrap interval (from two seeds), and the per-seed values themselves (as
    computed, NaN included) so that any other statistic can be computed later without
    retraining. The statistics are over the seeds with a finite score; `missing` counts the
    others (absent when there are none), so that a seed without a score is shown, not hidden."""
    values = np.asarray(per_seed, dtype=float).ravel()
    scored = finite(values)
    n = len(scored)
    out = {"seeds": len(values), "per_seed": [float(v) for v in values],
           "mean": round(float(scored.mean()), 6) if n else float("nan"),
           "se": round(float(scored.std(ddof=1) / np.sqrt(n)), 6) if n > 1 else 0.0}
    if n < len(values):
        out["missing"] = len(values) - n
    ci = iqm_ci([scored])
    if ci is not None:
        out["iqm"], out["iqm_low"], out["iqm_high"] = (round(v, 6) for v in ci)
    return out


def scored_seeds(d: dict) -> int:
    """How many seeds of a `describe` summary have a finite score."""
    return d.get("seeds", 0) - d.get("missing", 0)


LONG_NUMBER = 1e9  # from here on a summary's numbers are written with an exponent


def format_summary(d: dict, digits: int = 2, unit: str = "seed") -> str:
    """"m ± se; IQM i [lo, hi]" for several seeds, "m (1 seed)" for one: a single seed has no
    spread to show, and an SE of 0 would claim one. Seeds without a score are counted after
    the figures; a run with none says "no value". `unit`: what the values are of (a seed, a
    participant)."""
    total, n = d.get("seeds", 0), scored_seeds(d)
    if n == 0:
        return "no value" + (f" ({total} {unit}{'s' if total > 1 else ''} without a final score)" if total else "")

    def number(x: float) -> str:  # a diverged seed's 3e38 in exponent form, not 39 digits in a cell
        return f"{x:.{digits}e}" if abs(x) >= LONG_NUMBER else f"{x:.{digits}f}"

    if n == 1:
        text = f"{number(d['mean'])} (1 {unit})"
    else:
        text = f"{number(d['mean'])} ± {number(d['se'])}"
        if "iqm" in d:
            text += f"; IQM {number(d['iqm'])} [{number(d['iqm_low'])}, {number(d['iqm_high'])}]"
    if n < total:
        text += f" ({total - n} of {total} {unit}s without a final score)"
    return text
