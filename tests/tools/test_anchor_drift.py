"""Tests for tools/anchor_drift.py: on a synthetic row whose pelvis goes twice as far as its anchor, at a
known angle, the tool reports the hand-computed travel ratio, heading error and per-frame errors; a
directory that is not a finished row exits 2 naming it. With --kinks, a row that meets its anchor by moving
the anchor frame alone (a spike) shows the hand-computed kink and toe slide at the anchor and none far from
it, while a row that walks smoothly through the same anchor shows none anywhere."""

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


def write_spike_row(row_dir, spike):
    """One replicate, one task of 60 frames: every joint still, toes on the floor (y = 0.01), the pelvis at
    y = 0.9; a keyframe anchor on the pelvis at frame 30. The whole body at frame 30 is moved by `spike` m
    along x (ProjFlow's kinematic metric moves a frame's joints together), as a spike."""
    os.makedirs(row_dir)
    T, J = 60, 22
    joints = np.zeros((1, T, J, 3), np.float32)
    joints[0, :, 0, 1] = 0.9
    joints[0, :, 10:12, 1] = 0.01
    joints[0, 30, :, 0] += spike
    with h5py.File(os.path.join(row_dir, "samples_r0.h5"), "w") as f:
        f["joints"] = joints
        f["lengths"] = np.array([T], np.int64)
        item = f.create_group("control/sample_000000/item_000")
        item.attrs["type"] = "keyframe"
        item["frames"] = np.array([30], np.int64)
        item["joints"] = np.array([0], np.int64)
        item["values"] = joints[0, 30:31, 0:1].astype(np.float64)


class AnchorKinksTest(unittest.TestCase):
    def cells(self, out, name):
        line = [l for l in out.stdout.splitlines() if l.startswith(f"| {name}")][0]
        return [c.strip() for c in line.strip("|").split("|")][1:]

    def test_spike_against_smooth(self):
        with tempfile.TemporaryDirectory() as tmp:
            spiky, smooth = os.path.join(tmp, "spiky-1"), os.path.join(tmp, "smooth-2")
            write_spike_row(spiky, 0.1)
            write_spike_row(smooth, 0.0)
            out = run_tool("--kinks", spiky, smooth)
            self.assertEqual(out.returncode, 0, out.stderr)
            s, m = self.cells(out, "spiky-1"), self.cells(out, "smooth-2")
            # at the anchor |x29 - 2 x30 + x31| = 2 * 10 cm, one frame away 10 cm, averaged over frames
            # 27-29 and 31-33 (two of six frames touch the spike): 10 * 2 / 6 cm; far from it nothing
            self.assertAlmostEqual(float(s[0]), 20.0, places=1)
            self.assertAlmostEqual(float(s[1]), 10.0 * 2 / 6, places=1)
            self.assertEqual(float(s[2]), 0.0)
            self.assertAlmostEqual(float(s[3]), 20.0, places=1)          # the toes moved with the frame
            # contact steps 29->30 and 30->31 slide 10 cm each; near = the 8 steps 26..33 of 2 toes
            self.assertAlmostEqual(float(s[6]), 10.0 * 4 / 16, places=2)
            self.assertEqual(float(s[7]), 0.0)
            self.assertTrue(all(float(c) == 0.0 for c in m), m)

    def test_bad_contact_exits_2(self):
        with tempfile.TemporaryDirectory() as tmp:
            row = os.path.join(tmp, "row-1")
            write_spike_row(row, 0.1)
            out = run_tool("--kinks", "--contact", "0", row)
            self.assertEqual(out.returncode, 2)
            self.assertIn("--contact", out.stderr)


if __name__ == "__main__":
    unittest.main()
