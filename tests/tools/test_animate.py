"""Tests for tools/animate.py and motionio.read_control: a motion file with constraints in /control
(keyframes, a trajectory, a planar path, 2D observations with their camera) animates to MP4 (skipped
when ffmpeg is absent) and GIF with one video frame per motion frame, the targets drawn in their
colour, the source beside it, and bad input exits 2."""

import os
import shutil
import subprocess
import sys
import tempfile
import unittest

from tools_test_util import TOOLS, require_modules

require_modules("numpy", "h5py", "matplotlib", "PIL.Image")
import numpy as np  # noqa: E402
import h5py  # noqa: E402
from PIL import Image  # noqa: E402
import motionio  # noqa: E402
from test_figures import walk, s_path  # noqa: E402

FFMPEG = shutil.which("ffmpeg")
TARGET_RGB = np.array([0x2C, 0xA0, 0x2C])
T = 24


def run_animate(*args):
    return subprocess.run([sys.executable, os.path.join(TOOLS, "animate.py"), *map(str, args)],
                          capture_output=True, text=True, timeout=600)


def green_pixels(rgb):
    return int((np.abs(rgb[..., :3].astype(int) - TARGET_RGB).max(axis=-1) < 40).sum())


def write_item(g, kind, **kw):
    g.attrs["type"] = kind
    for key, v in kw.items():
        if key in ("frames_attr",):
            g.attrs["frames"] = v
        elif isinstance(v, str):
            g.attrs[key] = v
        elif v.dtype == object:
            g.create_dataset(key, data=v, dtype=h5py.string_dtype())
        else:
            g.create_dataset(key, data=v)


def build(tmp):
    """A two-sample 'generate output' and the dataset it came from."""
    src_clips = [walk(T, s_path), walk(T, lambda t: (0.05 * t, 0.0), phase=1.0)]
    data = os.path.join(tmp, "data.h5")
    motionio.write_motion(data, np.stack(src_clips), [T, T], ["clipA", "clipB"], ["test", "test"],
                          [["a person walks along an S"], ["a person walks sideways"]])
    gen = [c + np.array([0.02, 0.0, 0.01], np.float32) for c in src_clips]
    path = os.path.join(tmp, "gen.h5")
    motionio.write_motion(path, np.stack(gen), [T, T], ["clipA#0", "clipB#1"], ["sample", "sample"],
                          [["a person walks along an S"], ["a person walks sideways"]])
    with h5py.File(path, "a") as f:
        c = f.create_group("control")
        c.attrs["format"] = "motionctl.sample_constraints"
        c.attrs["format_version"] = np.int64(1)
        c.create_dataset("frames", data=np.array([T, T], np.int32))
        s0 = c.create_group("sample_000000")
        write_item(s0.create_group("item_000"), "keyframe", frames=np.array([0, 12, 23], np.int32),
                   joints=np.array([0, 20], np.int32), values=src_clips[0][[0, 12, 23]][:, [0, 20]].astype(np.float64),
                   name="keys")
        write_item(s0.create_group("item_001"), "trajectory", joints=np.array([b"r_wrist"], dtype=object),
                   frames_attr="all", values=src_clips[0][:, 21].astype(np.float64), name="wrist path")
        s1 = c.create_group("sample_000001")
        write_item(s1.create_group("item_000"), "planar_root", values=src_clips[1][:, 0][:, [0, 2]].astype(np.float64))
        cam = np.array([1.0, 10.0, 20.0, 0.0])
        uv = np.stack([motionio_project(src_clips[1][t:t + 1, [15]], cam)[0] for t in range(T)])
        write_item(s1.create_group("item_001"), "camera_2d", joints=np.array([15], np.int32), camera=cam,
                   values=uv)
    motionio.seal_h5_file(path)
    return data, path


def motionio_project(points, cam):
    import figures
    return figures.project(np.asarray(points, np.float64), cam)


class ReadControl(unittest.TestCase):
    def test_items_frames_joints_values(self):
        tmp = tempfile.mkdtemp(prefix="animate_rc_")
        try:
            data, path = build(tmp)
            m = motionio.read_motion(path)
            items = motionio.read_control(path, m)
            self.assertEqual([[i["type"] for i in s] for s in items],
                             [["keyframe", "trajectory"], ["planar_root", "camera_2d"]])
            key, traj = items[0]
            self.assertEqual(key["frames"].tolist(), [0, 12, 23])
            self.assertEqual(key["joints"], [0, 20])
            self.assertEqual(traj["joints"], [21])                 # a name resolved to its index
            self.assertEqual(traj["frames"].tolist(), list(range(T)))
            self.assertEqual(items[1][0]["axes"], [0, 2])
            np.testing.assert_array_equal(items[1][1]["camera"], [1.0, 10.0, 20.0, 0.0])
            self.assertEqual(motionio.read_control(data, motionio.read_motion(data)), [[], []])
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


class Animate(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="animate_")
        cls.data, cls.gen = build(cls.tmp)

    @classmethod
    def tearDownClass(cls):
        shutil.rmtree(cls.tmp, ignore_errors=True)

    def test_gif_has_every_other_frame_and_shows_targets(self):
        out = os.path.join(self.tmp, "gif")
        r = run_animate(self.gen, "--out", out, "--all", "--format", "gif", "--source", self.data)
        self.assertEqual(r.returncode, 0, r.stderr)
        paths = r.stdout.split()
        self.assertEqual([os.path.basename(p) for p in paths], ["0000_clipA_0.gif", "0001_clipB_1.gif"])
        for p in paths:
            with Image.open(p) as im:
                self.assertEqual(im.n_frames, T // 2)          # 20 fps motion at 10 fps
                w, h = im.size
                self.assertLessEqual(max(w, h), 4000)
                im.seek(0)                                    # frame 0: keyframe 0 is highlighted
                self.assertGreater(green_pixels(np.asarray(im.convert("RGB"))), 30, p)
        # Sample 0: sample, source, top-down; sample 1 adds its camera view (4 panels): wider.
        with Image.open(paths[0]) as a, Image.open(paths[1]) as b:
            self.assertGreater(b.size[0], a.size[0])

    @unittest.skipIf(FFMPEG is None, "ffmpeg is not installed")
    def test_mp4_one_video_frame_per_motion_frame(self):
        out = os.path.join(self.tmp, "mp4")
        r = run_animate(self.gen, "--out", out, "--clips", "0", "--format", "mp4")
        self.assertEqual(r.returncode, 0, r.stderr)
        path = os.path.join(out, "0000_clipA_0.mp4")
        self.assertEqual(r.stdout.split(), [path])
        probe = subprocess.run(["ffprobe", "-v", "error", "-count_frames", "-select_streams", "v:0", "-show_entries",
                                "stream=nb_read_frames,width,height,codec_name", "-of", "csv=p=0", path],
                               capture_output=True, text=True, timeout=120)
        codec, width, height, frames = probe.stdout.strip().split(",")
        self.assertEqual(codec, "h264")
        self.assertEqual(int(frames), T)
        self.assertEqual(int(width) % 2, 0)
        self.assertLess(os.path.getsize(path), 2_000_000)
        # The frame at the middle keyframe (t = 12) shows the targets.
        frame = subprocess.run(["ffmpeg", "-v", "error", "-i", path, "-vf", "select=eq(n\\,12)", "-vframes", "1",
                                "-f", "rawvideo", "-pix_fmt", "rgb24", "-"], capture_output=True, timeout=120).stdout
        rgb = np.frombuffer(frame, np.uint8).reshape(int(height), int(width), 3)
        self.assertGreater(green_pixels(rgb), 30)

    def test_bad_input(self):
        r = run_animate(os.path.join(self.tmp, "nope.h5"), "--out", os.path.join(self.tmp, "x"), "--format", "gif")
        self.assertEqual(r.returncode, 2)
        self.assertIn("nope.h5", r.stderr)
        self.assertNotIn("Traceback", r.stderr)
        r = run_animate(self.gen, "--out", os.path.join(self.tmp, "x"), "--ids", "missing", "--format", "gif")
        self.assertEqual(r.returncode, 2)
        self.assertIn("missing", r.stderr)
        r = run_animate(self.gen, "--out", os.path.join(self.tmp, "x"), "--format", "avi")
        self.assertEqual(r.returncode, 2)


if __name__ == "__main__":
    unittest.main()
