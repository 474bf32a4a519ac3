"""Tests for tools/realism_check.py: on synthetic rows, a row shifted away from the reference is decided
worse on FID and KID, a row that is the other plus tiny noise is undecided; FID equals the textbook
formula; bad input exits 2 naming the file."""

import os
import subprocess
import sys
import tempfile
import unittest

from tools_test_util import TOOLS, require_modules

require_modules("numpy", "h5py")
import numpy as np  # noqa: E402
import h5py  # noqa: E402

sys.path.insert(0, TOOLS)
import realism_check  # noqa: E402


def run_tool(*args):
    return subprocess.run([sys.executable, os.path.join(TOOLS, "realism_check.py"), *map(str, args)],
                          capture_output=True, text=True, timeout=300)


def write_row(row_dir, reps):
    os.makedirs(row_dir)
    with h5py.File(os.path.join(row_dir, "samples.h5"), "w") as f:
        for r, x in enumerate(reps):
            f.create_dataset(f"r{r}/motion", data=x)


class RealismCheck(unittest.TestCase):
    def setUp(self):
        self.tmp = tempfile.TemporaryDirectory()
        d = self.tmp.name
        rng = np.random.default_rng(1)
        self.ref = os.path.join(d, "ref.h5")
        with h5py.File(self.ref, "w") as f:
            f.create_dataset("embeddings/gt_motion", data=rng.standard_normal((300, 6)))
        base = [0.3 + rng.standard_normal((64, 6)) for _ in range(2)]
        write_row(os.path.join(d, "near"), base)
        write_row(os.path.join(d, "far"), [x + 2.0 for x in base])
        write_row(os.path.join(d, "twin"), [x + 1e-3 * rng.standard_normal(x.shape) for x in base])

    def tearDown(self):
        self.tmp.cleanup()

    def test_fid_matches_the_textbook_formula(self):
        rng = np.random.default_rng(2)
        y, x = rng.standard_normal((200, 5)), 0.5 + 1.3 * rng.standard_normal((40, 5))
        ref = realism_check.Reference(y)
        cx, cy = np.cov(x, rowvar=False), np.cov(y, rowvar=False)
        w, v = np.linalg.eig(cx @ cy)
        textbook = ((x.mean(0) - y.mean(0)) ** 2).sum() + np.trace(cx) + np.trace(cy) - 2 * np.sqrt(w).real.sum()
        # The textbook's eigenvalues of the non-symmetric product carry ~1e-7 of rounding
        # that depends on the CPU's BLAS kernels (5.4e-7 on an Intel Xeon, 2026-11-29).
        self.assertAlmostEqual(ref.fid(x), textbook, places=5)

    def test_decided_and_undecided(self):
        d = self.tmp.name
        out = run_tool("--reference", self.ref, f"{d}/far:{d}/near", f"{d}/twin:{d}/near")
        self.assertEqual(out.returncode, 0, out.stderr)
        lines = [l for l in out.stdout.splitlines() if l.startswith("| far") or l.startswith("| twin")]
        self.assertEqual(len(lines), 2, out.stdout)
        far, twin = lines
        self.assertEqual(far.count("**decided**"), 2, far)  # worse on both FID and KID
        self.assertIn("| +", far)                             # a - b > 0: the far row is less realistic
        self.assertNotIn("decided", twin)

    def test_bad_input_exits_2(self):
        d = self.tmp.name
        out = run_tool("--reference", self.ref, f"{d}/nosuch:{d}/near")
        self.assertEqual(out.returncode, 2)
        self.assertIn("nosuch", out.stderr)
        out = run_tool("--reference", os.path.join(d, "missing.h5"), f"{d}/far:{d}/near")
        self.assertEqual(out.returncode, 2)
        self.assertIn("missing.h5", out.stderr)
        out = run_tool("--reference", self.ref, "--dataset", "nope", f"{d}/far:{d}/near")
        self.assertEqual(out.returncode, 2)
        self.assertIn("nope", out.stderr)


if __name__ == "__main__":
    unittest.main()
