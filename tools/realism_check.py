#!/usr/bin/python3
"""Paired realism tests between table rows, on FID and on KID, from the rows' stored
evaluator embeddings (samples.h5, docs/formats.md) and a reference set of embeddings.

It resamples the way the replay resamples set-level metrics (experiments/paired.cpp):
- half-samples of ceil(n/2) tasks, drawn without replacement, the same tasks for both
  rows;
- the statistic averaged over the replicates both rows have;
- the 95% percentile interval re-centred on the full-sample estimate.

Without the task-group strata: a diagnostic, not the replay. It prints, per pair, the
difference a - b with its interval and whether the interval excludes 0. Used for
docs/choices.md ("Bootstrap strata and draws"), to ask whether KID, which is unbiased,
decides realism claims that FID leaves undecided.

  tools/realism_check.py --reference runs/eval/<eval run>/metrics.h5 \\
      runs/standard_rows/tmd-*:runs/standard_rows/masked_tokens-*

Each positional argument is ROW_A:ROW_B (row run directories, globs allowed if they
match one directory). The reference is an HDF5 file with a 2-D dataset of embeddings:
`embeddings/gt_motion` (what `motionctl eval` writes) unless --dataset says otherwise.

Only numpy and h5py (Debian's /usr/bin/python3).
"""

import argparse
import glob
import os
import sys

import h5py
import numpy as np


def fail(message):
    """Bad input: the message on stderr, exit code 2 (the project's convention)."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def one_dir(pattern):
    hits = sorted(glob.glob(pattern))
    if len(hits) != 1:
        fail(f"'{pattern}' matches {len(hits)} directories; give exactly one row run directory")
    return hits[0]


def read_row(row_dir):
    """Per replicate [n, D] motion embeddings of a finished row."""
    path = os.path.join(row_dir, "samples.h5")
    if not os.path.isfile(path):
        fail(f"{row_dir}: no samples.h5; give the run directory of a finished table row")
    try:
        with h5py.File(path, "r") as f:
            reps = []
            r = 0
            while f"r{r}" in f:
                if "motion" not in f[f"r{r}"]:
                    fail(f"{path}: replicate r{r} has no 'motion' embeddings; re-run the row")
                reps.append(np.asarray(f[f"r{r}/motion"], dtype=np.float64))
                r += 1
    except OSError as e:
        fail(f"{path}: cannot read ({e}); delete the row's run directory and re-run reproduce")
    if not reps:
        fail(f"{path}: no replicates (r0, r1, ...); re-run the row")
    return reps


class Reference:
    """FID and KID against a fixed reference, with its moments and kernel sums precomputed."""

    def __init__(self, y):
        if y.ndim != 2 or len(y) < 2:
            fail(f"the reference must be a 2-D array of at least 2 embeddings, got shape {y.shape}")
        self.y = y
        self.mean = y.mean(0)
        w, v = np.linalg.eigh(np.cov(y, rowvar=False))
        self.sqrt_cov = (v * np.sqrt(np.clip(w, 0, None))) @ v.T
        self.trace = float(np.trace(np.cov(y, rowvar=False)))
        k = self.kernel(y, y)
        m = len(y)
        self.kyy = (k.sum() - np.trace(k)) / (m * (m - 1))

    def kernel(self, a, b):
        return (a @ b.T / a.shape[1] + 1.0) ** 3  # KID's cubic polynomial kernel

    def fid(self, x):
        """Frechet distance; Tr sqrt(C_x C_ref) from the n x n problem, as experiments/paired.cpp."""
        n = len(x)
        mx = x.mean(0)
        xc = x - mx
        yc = xc @ self.sqrt_cov
        ev = np.linalg.eigvalsh(yc @ yc.T / (n - 1))
        return float(((mx - self.mean) ** 2).sum() + (xc ** 2).sum() / (n - 1) + self.trace
                     - 2.0 * np.sqrt(np.clip(ev, 0, None)).sum())

    def kid(self, x):
        n, m = len(x), len(self.y)
        kxx = self.kernel(x, x)
        return float((kxx.sum() - np.trace(kxx)) / (n * (n - 1)) + self.kyy
                     - 2.0 * self.kernel(x, self.y).sum() / (n * m))


def paired_test(ref, a, b, metric, draws, rng):
    """(estimate, lo, hi) of metric(a) - metric(b), half-samples without replacement."""
    n = len(a[0])
    reps = min(len(a), len(b))
    if any(len(x) != n for x in a[:reps] + b[:reps]):
        fail("the two rows have different task counts; they are not paired")
    stat = getattr(ref, metric)

    def diff(idx):
        return float(np.mean([stat(a[r][idx]) - stat(b[r][idx]) for r in range(reps)]))

    est = diff(np.arange(n))
    d = np.array([diff(np.sort(rng.permutation(n)[:(n + 1) // 2])) for _ in range(draws)])
    shift = est - d.mean()
    lo, hi = np.percentile(d, [2.5, 97.5]) + shift
    return est, float(lo), float(hi)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("pairs", nargs="+", help="ROW_A:ROW_B row run directories (globs matching one each)")
    ap.add_argument("--reference", required=True, help="HDF5 file with the reference embeddings")
    ap.add_argument("--dataset", default="embeddings/gt_motion", help="dataset inside --reference")
    ap.add_argument("--draws", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    if args.draws < 10:
        fail(f"--draws {args.draws}: need at least 10")
    if not os.path.isfile(args.reference):
        fail(f"--reference '{args.reference}' does not exist; give the metrics.h5 of a `motionctl eval` run")
    try:
        with h5py.File(args.reference, "r") as f:
            if args.dataset not in f:
                fail(f"{args.reference}: no dataset '{args.dataset}'; name one with --dataset")
            ref = Reference(np.asarray(f[args.dataset], dtype=np.float64))
    except OSError as e:
        fail(f"{args.reference}: cannot read ({e})")
    rng = np.random.default_rng(args.seed)
    print("| row a | row b | tasks | FID a − b [95%] | KID a − b [95%] |")
    print("|---|---|---:|---|---|")
    for pair in args.pairs:
        if pair.count(":") != 1:
            fail(f"'{pair}': give ROW_A:ROW_B")
        da, db = (one_dir(p) for p in pair.split(":"))
        a, b = read_row(da), read_row(db)
        cells = []
        for metric in ("fid", "kid"):
            est, lo, hi = paired_test(ref, a, b, metric, args.draws, rng)
            decided = " **decided**" if lo > 0 or hi < 0 else ""
            cells.append(f"{est:+.4g} [{lo:+.4g}, {hi:+.4g}]{decided}")
        print(f"| {os.path.basename(da)} | {os.path.basename(db)} | {len(a[0])} | {cells[0]} | {cells[1]} |")


if __name__ == "__main__":
    main()
