"""Tests for tools/anchor_drift.py: on a synthetic row whose pelvis goes twice as far as its anchor, at a
known angle, the tool reports the hand-computed travel ratio, heading error and per-frame errors; a
directory that is not a finished row exits 2 naming it."""

import math
import os
import subprocess
import sys
import tempfile
import unittest

from tools_test_util import TOOLS, require_modules

require_modules("numpy", "h5py")
import numpy as np  # noqa: E402
import h5py  # noqa: E402


def run_tool(*args):
    return subprocess.run([sys.executable, os.path.join(TOOLS, "anchor_drift.py"), *map(str, args)],
                          capture_output=True, text=True, timeout=120)


def write_row(row_dir, angle_deg, scale):
    """One replicate, one task: the pelvis walks in a straight line along +z at 0.02 m per frame for
    196 frames; the anchors (frames 10 and 150) lie on a line rotated by angle_deg, 1/scale as far."""
    os.makedirs(row_dir)
    T, J = 196, 22
    joints = np.zeros((1, T, J, 3), np.float32)
    joints[0, :, 0, 2] = 0.02 * np.arange(T)
    frames = np.array([10, 150], np.int64)
    a = math.radians(angle_deg)
    direction = np.array([math.sin(a), 0.0, math.cos(a)])
    values = np.stack([0.02 * t / scale * direction for t in frames])[:, None, :]
    with h5py.File(os.path.join(row_dir, "samples_r0.h5"), "w") as f:
        f["joints"] = joints
        item = f.create_group("control/sample_000000/item_000")
        item.attrs["type"] = "keyframe"
        item["frames"] = frames
        item["joints"] = np.array([0], np.int64)
        item["values"] = values
    return joints, frames, values


class AnchorDriftTest(unittest.TestCase):
    def test_hand_computed_row(self):
        with tempfile.TemporaryDirectory() as tmp:
            row = os.path.join(tmp, "row-abc")
            joints, frames, values = write_row(row, angle_deg=40.0, scale=2.0)
            out = run_tool(row)
            self.assertEqual(out.returncode, 0, out.stderr)
            line = [l for l in out.stdout.splitlines() if l.startswith("| row-abc")][0]
            cells = [c.strip() for c in line.strip("|").split("|")]
            # frames 0-19 holds the anchor at frame 10, 120-159 the one at 150
            e10 = np.linalg.norm(joints[0, 10, 0] - values[0, 0])
            e150 = np.linalg.norm(joints[0, 150, 0] - values[1, 0])
            self.assertAlmostEqual(float(cells[1]), e10, places=2)
            self.assertEqual(cells[2], "–")
            self.assertAlmostEqual(float(cells[5]), e150, places=2)
            self.assertEqual(cells[7], "1")           # one Root-3D task moved >= 0.5 m (1.5 m)
            self.assertAlmostEqual(float(cells[8]), 2.0, places=2)  # went twice as far
            self.assertEqual(cells[9], "40")          # 40 degrees off
            self.assertEqual(cells[10], "0.00")       # not within 30 degrees
            # a short target (under --min-travel) is not a heading task
            out = run_tool(row, "--min-travel", "2.0")
            line = [l for l in out.stdout.splitlines() if l.startswith("| row-abc")][0]
            self.assertEqual([c.strip() for c in line.strip("|").split("|")][7], "0")

    def test_not_a_row_exits_2_naming_it(self):
        with tempfile.TemporaryDirectory() as tmp:
            out = run_tool(tmp)
            self.assertEqual(out.returncode, 2)
            self.assertIn(tmp, out.stderr)
            self.assertIn("samples_r", out.stderr)


if __name__ == "__main__":
    unittest.main()
