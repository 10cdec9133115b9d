#!/usr/bin/env python3
"""How tight can a per-texel bound be? Python standard library only.

Texels under a random straight shadow edge, sampled by visq's jittered
pattern (rows of floor/ceil(N / rows) equal-area cells, one uniform sample
each). For each N it prints the median bound over the median error for:
  gauss-true-V    1.96 sigma with the true variance (no finite-sample bound
                  can be this tight; the CLT's limit)
  bennett-true-V  Bennett's inequality at the true variance
  bennett-E[K]    Bennett at the expected split-pair count (the pairs'
                  overstatement of the variance, no sampling noise)
  bennett-K_up    Bennett at the split pairs' upper limit (what BoundTexels
                  does, before taking the count's interval where smaller)
Usage: texel_bound_floor.py [--trials 150] [--n 64 256 1024]
"""
import argparse
import math
import random
import statistics


def pattern(n):
    rows = max(1, round(math.sqrt(n)))
    cells = []
    for r in range(rows):
        first, end = r * n // rows, (r + 1) * n // rows
        count = end - first
        for c in range(count):
            cells.append((c / count, (c + 1) / count, first / n, end / n))
    return cells


def binom_cdf(k, m, p):
    if p <= 0.0:
        return 1.0
    if p >= 1.0:
        return 1.0 if k >= m else 0.0
    total = 0.0
    for i in range(0, k + 1):
        total += math.exp(math.lgamma(m + 1) - math.lgamma(i + 1) - math.lgamma(m - i + 1)
                          + i * math.log(p) + (m - i) * math.log1p(-p))
    return total


def pairs_upper(k, m, delta):
    """Clopper-Pearson upper limit of the mean split-pair count, one count wider."""
    k = min(k + 1, m)
    if k >= m:
        return float(m)
    lo, hi = 0.0, 1.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if binom_cdf(k, m, mid) > delta:
            lo = mid
        else:
            hi = mid
    return hi * m


def bennett(variance, delta):
    if variance <= 0.0:
        return 0.0
    budget = math.log(2.0 / delta)
    lo, hi = 0.0, 1.0
    h = lambda t: variance * ((1 + t / variance) * math.log1p(t / variance) - t / variance)
    while h(hi) < budget:
        hi *= 2.0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if h(mid) < budget:
            lo = mid
        else:
            hi = mid
    return hi


def cell_fraction(cell, a, b, c, grid=24):
    u0, u1, v0, v1 = cell
    inside = 0
    for i in range(grid):
        for j in range(grid):
            u = u0 + (u1 - u0) * (i + 0.5) / grid
            v = v0 + (v1 - v0) * (j + 0.5) / grid
            inside += a * u + b * v >= c
    return inside / (grid * grid)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--trials", type=int, default=150)
    parser.add_argument("--n", type=int, nargs="+", default=[64, 256, 1024])
    parser.add_argument("--seed", type=int, default=2)
    args = parser.parse_args()
    rng = random.Random(args.seed)
    failure = 0.05
    for n in args.n:
        cells = pattern(n)
        m = n // 2
        rows = []
        for _ in range(args.trials):
            angle = rng.uniform(0.0, 2.0 * math.pi)
            a, b = math.cos(angle), math.sin(angle)
            c = 0.5 * a + 0.5 * b + rng.uniform(-0.45, 0.45)
            p = []
            for cell in cells:
                u0, u1, v0, v1 = cell
                # Only cells the edge can cross need integrating.
                corners = [a * u + b * v >= c for u in (u0, u1) for v in (v0, v1)]
                p.append(float(corners[0]) if all(x == corners[0] for x in corners) else cell_fraction(cell, a, b, c))
            variance = sum(q * (1 - q) for q in p)
            expected_split = sum(p[2 * i] + p[2 * i + 1] - 2 * p[2 * i] * p[2 * i + 1] for i in range(m))
            x = [1 if rng.random() < q else 0 for q in p]
            split = sum(x[2 * i] != x[2 * i + 1] for i in range(m))
            error = abs(sum(x) / n - sum(p) / n)
            rows.append((variance, expected_split, split, error))
        median_error = statistics.median(r[3] for r in rows)
        share_pairs, share_count = 0.2 * failure, 0.3 * failure
        figures = {
            "gauss-true-V": [1.96 * math.sqrt(r[0]) / n for r in rows],
            "bennett-true-V": [bennett(r[0], failure) / n for r in rows],
            "bennett-E[K]": [bennett(r[1], failure) / n for r in rows],
            "bennett-K_up": [bennett(pairs_upper(r[2], m, share_pairs), share_count) / n for r in rows],
        }
        print(f"N {n}: median error {median_error:.5f} over {args.trials} texels under an edge")
        for name, bounds in figures.items():
            print(f"  {name:15s} median bound {statistics.median(bounds):.5f}  "
                  f"{statistics.median(bounds) / median_error:5.1f}x the median error")


if __name__ == "__main__":
    main()
