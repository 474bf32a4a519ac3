"""Tests for tools/render_motion.py and tools/dataset_stats.py: they run as subprocesses on a
tiny synthetic motion file, write real PNG/GIF/JSON files, and exit 2 on bad input."""

import json
import os
import shutil
import subprocess
import sys
import tempfile
import unittest

from tools_test_util import TOOLS, require_modules

require_modules("numpy", "h5py", "matplotlib")
import numpy as np  # noqa: E402
import h5py  # noqa: E402
import matplotlib  # noqa: E402
matplotlib.use("Agg")
import matplotlib.image as plt_image  # noqa: E402
import motionio  # noqa: E402

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def run_tool(name, *args):
    return subprocess.run([sys.executable, os.path.join(TOOLS, name), *map(str, args)],
                          capture_output=True, text=True, timeout=120)


def rest_pose(skeleton):
    """Joint positions of the rest pose, feet on the floor (no rotations, so no FK needed)."""
    parents, dirs, lengths = skeleton["parents"], skeleton["rest_directions"], skeleton["bone_lengths"]
    pos = np.zeros((len(parents), 3))
    for j in range(1, len(parents)):
        pos[j] = pos[parents[j]] + dirs[j] * lengths[j]
    pos[:, 1] -= pos[:, 1].min()
    return pos


def synthetic_clip(skeleton, frames, velocity, bob):
    """The rest pose translated along a straight line with a little vertical bob."""
    t = np.arange(frames)[:, None, None] / 20.0
    pose = rest_pose(skeleton)[None]
    offset = np.concatenate([velocity[0] * t, bob * np.sin(6.0 * t) ** 2, velocity[1] * t], axis=-1)
    return (pose + offset).astype(np.float32)


class RenderAndStats(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="render_")
        cls.file = os.path.join(cls.tmp, "tiny.h5")
        skel = motionio.humanml3d_skeleton()
        clips = [synthetic_clip(skel, 30, (0.0, 1.2), 0.05), synthetic_clip(skel, 24, (0.8, 0.0), 0.0),
                 synthetic_clip(skel, 40, (0.0, 0.0), 0.1)]
        lengths = [len(c) for c in clips]
        joints = np.zeros((3, max(lengths), 22, 3), np.float32)
        for i, c in enumerate(clips):
            joints[i, :len(c)] = c
        motionio.write_motion(
            cls.file, joints, lengths, ["walk_fwd", "walk/side#1", "bounce"], ["train", "train", "test"],
            [["a person walks forward", "someone walks"], ["a person steps to the left"], ["jumping in place"]],
            labels=["walk", "walk", "jump"], vocab=list(motionio.VOCAB_SPECIALS) + ["a", "forward", "person", "someone", "walks"],
            provenance={"generator": "test_render_tools.py", "version": "1", "seed": 3})

    @classmethod
    def tearDownClass(cls):
        shutil.rmtree(cls.tmp, ignore_errors=True)

    def assert_png(self, path):
        self.assertTrue(os.path.isfile(path), path)
        with open(path, "rb") as f:
            self.assertEqual(f.read(8), PNG_MAGIC, path)
        self.assertGreater(os.path.getsize(path), 1024, path)

    def test_render_strips_and_gifs(self):
        out = os.path.join(self.tmp, "render")
        r = run_tool("render_motion.py", self.file, "--out", out, "--clips", "0,1", "--frames", "4", "--gif")
        self.assertEqual(r.returncode, 0, r.stderr)
        printed = r.stdout.split()
        expected = [os.path.join(out, n) for n in
                    ("0000_walk_fwd.png", "0000_walk_fwd.gif", "0001_walk_side_1.png", "0001_walk_side_1.gif")]
        self.assertEqual(printed, expected)
        for path in expected:
            if path.endswith(".png"):
                self.assert_png(path)
            else:
                with open(path, "rb") as f:
                    self.assertIn(f.read(6), (b"GIF87a", b"GIF89a"))
                self.assertGreater(os.path.getsize(path), 1024)
        self.assertEqual(sorted(os.listdir(out)), sorted(os.path.basename(p) for p in expected))

    def test_long_strips_wrap_and_stay_bounded(self):
        out = os.path.join(self.tmp, "long")
        r = run_tool("render_motion.py", self.file, "--out", out, "--clips", "2", "--frames", "40")
        self.assertEqual(r.returncode, 0, r.stderr)
        img = plt_image.imread(os.path.join(out, "0002_bounce.png"))
        h, w = img.shape[:2]
        self.assertLessEqual(max(w, h), 4000)
        # 40 poses at 12 per line: four lines of fixed-size panels, not one 40-panel-wide strip.
        self.assertLess(w, 12 * 170 + 100)
        self.assertGreater(h, 4 * 210)

    def test_render_by_id_and_default_count(self):
        out = os.path.join(self.tmp, "by_id")
        r = run_tool("render_motion.py", self.file, "--out", out, "--ids", "bounce")
        self.assertEqual(r.returncode, 0, r.stderr)
        self.assert_png(os.path.join(out, "0002_bounce.png"))
        out = os.path.join(self.tmp, "count")
        r = run_tool("render_motion.py", self.file, "--out", out, "--count", "2")
        self.assertEqual(r.returncode, 0, r.stderr)
        self.assertEqual(len(os.listdir(out)), 2)

    def test_dataset_stats(self):
        out = os.path.join(self.tmp, "stats")
        r = run_tool("dataset_stats.py", self.file, "--out", out)
        self.assertEqual(r.returncode, 0, r.stderr)
        self.assertEqual(r.stdout.split(), [os.path.join(out, "dataset_stats.png"), os.path.join(out, "stats.json")])
        self.assert_png(os.path.join(out, "dataset_stats.png"))
        with open(os.path.join(out, "stats.json")) as f:
            s = json.load(f)
        self.assertEqual(s["num_clips"], 3)
        self.assertEqual(s["clips_per_split"], {"train": 2, "test": 1})
        self.assertAlmostEqual(s["length_frames"]["mean"], (30 + 24 + 40) / 3)
        self.assertEqual(s["length_frames"]["per_split_mean"], {"train": 27.0, "test": 40.0})
        self.assertEqual(s["vocab_size"], 5)
        self.assertEqual(s["captions"]["total"], 4)
        self.assertAlmostEqual(s["captions"]["per_clip_mean"], 4 / 3)
        self.assertEqual(s["labels"], {"jump": 1, "walk": 2})
        self.assertEqual(dict(s["top_words"])["a"], 2)
        # Clip 0 walks 1.2 m/s forward for 29 steps; clip 1 0.8 m/s; clip 2 stands.
        self.assertAlmostEqual(s["root_speed_mps"]["max"], 1.2, places=4)
        self.assertAlmostEqual(s["final_root_distance_m"]["max"], 1.2 * 29 / 20, places=4)
        lo, hi = s["joint_height_m"]["r_foot"]
        self.assertGreaterEqual(lo, -1e-6)
        self.assertGreater(s["joint_height_m"]["head"][0], 1.0)
        self.assertEqual(s["provenance"]["seed"], 3)


class BadInput(unittest.TestCase):
    def setUp(self):
        self.tmp = tempfile.mkdtemp(prefix="render_bad_")
        self.out = os.path.join(self.tmp, "out")

    def tearDown(self):
        shutil.rmtree(self.tmp, ignore_errors=True)

    def assert_rejected(self, path, *extra):
        for tool in ("render_motion.py", "dataset_stats.py"):
            r = run_tool(tool, path, "--out", self.out, *extra)
            self.assertEqual(r.returncode, 2, f"{tool}: {r.stdout}{r.stderr}")
            self.assertIn(path, r.stderr, tool)
            self.assertNotIn("Traceback", r.stderr, tool)
            self.assertFalse(os.path.exists(self.out), f"{tool} created output for bad input")

    def test_missing_file(self):
        self.assert_rejected(os.path.join(self.tmp, "does_not_exist.h5"))

    def test_not_a_motion_file(self):
        path = os.path.join(self.tmp, "other.h5")
        with h5py.File(path, "w") as f:
            f.create_dataset("x", data=np.arange(4))
        self.assert_rejected(path)

    def test_not_hdf5(self):
        path = os.path.join(self.tmp, "text.h5")
        with open(path, "w") as f:
            f.write("hello")
        self.assert_rejected(path)

    def test_clip_out_of_range(self):
        path = os.path.join(self.tmp, "one.h5")
        skel = motionio.humanml3d_skeleton()
        motionio.write_motion(path, [synthetic_clip(skel, 10, (0, 0), 0)], [10], ["a"], ["train"], [["x"]])
        r = run_tool("render_motion.py", path, "--out", self.out, "--clips", "5")
        self.assertEqual(r.returncode, 2)
        self.assertIn("out of range", r.stderr)
        self.assertFalse(os.path.exists(self.out))


if __name__ == "__main__":
    unittest.main()
