"""Figures measured once per training seed, summarised: what another seed of the same command
may give. Used by the studies that train a card several times (detection_seeds.py,
tdfanet_variants.py --seeds)."""

from __future__ import annotations

import math
import statistics

# Student's t quantile t(0.975, df) for df = 1..10; the normal quantile's 1.96 is too narrow for few seeds
T975 = (12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228)


def seed_summary(values: list[float]) -> dict:
    """Mean, sample standard deviation, min, max and the 95 % t-interval of the mean of one
    figure measured once per seed (no spread or interval from a single seed)."""
    n, mean = len(values), statistics.fmean(values)
    out = {"n": n, "mean": mean, "min": min(values), "max": max(values), "std": None, "interval": None}
    if n > 1:
        if n - 1 > len(T975):
            raise ValueError(f"{n} seeds: the t table covers up to {len(T975) + 1}")
        std = statistics.stdev(values)
        half = T975[n - 2] * std / math.sqrt(n)
        out.update(std=std, interval=[mean - half, mean + half])
    return out


def ranking(differences: list[float]) -> str:
    """Whether paired per-seed differences a - b (same seed, same data) rank a above b: "a" when
    the t-interval of their mean lies above 0, "b" when below, "not resolved" when it holds 0
    (or with one seed)."""
    s = seed_summary(differences)
    if s["interval"] is None or s["interval"][0] <= 0 <= s["interval"][1]:
        return "not resolved"
    return "a" if s["interval"][0] > 0 else "b"


def difference_of_means(a: list[float], b: list[float]) -> dict:
    """mean(a) - mean(b) of one figure measured once per seed on two unpaired sets of runs (two
    cards trained with the same command), with its 95 % Welch interval: Student's t at the
    Welch-Satterthwaite degrees of freedom, rounded down and capped at 10 (both widen it). No interval
    unless both sides have at least 2 seeds."""
    sa, sb = seed_summary(a), seed_summary(b)
    out = {"mean": sa["mean"] - sb["mean"], "interval": None, "df": None}
    if sa["std"] is None or sb["std"] is None:
        return out
    va, vb = sa["std"] ** 2 / len(a), sb["std"] ** 2 / len(b)
    if va + vb == 0:
        return {**out, "interval": [out["mean"], out["mean"]], "df": len(a) + len(b) - 2}
    df = (va + vb) ** 2 / (va**2 / (len(a) - 1) + vb**2 / (len(b) - 1))
    whole = min(max(int(df), 1), len(T975))
    half = T975[whole - 1] * math.sqrt(va + vb)
    return {**out, "interval": [out["mean"] - half, out["mean"] + half], "df": df}
