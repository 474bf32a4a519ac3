"""Tests for tools/humanml3d_to_h5.py: a miniature HumanML3D folder round-trips exactly,
the real reference clip matches the built-in skeleton, and bad input exits with code 2."""

import os
import re
import shutil
import subprocess
import sys
import tempfile
import unittest

from tools_test_util import REPO, TOOLS, require_modules

require_modules("numpy", "h5py")  # h5py: the tools need it
import numpy as np  # noqa: E402

CONVERTER = os.path.join(TOOLS, "humanml3d_to_h5.py")
REAL_CLIP = os.path.join(REPO, "..", "shared", "reference", "humanml3d", "012314_new_joints.npy")
import motionio  # noqa: E402


def run_converter(*args):
    return subprocess.run([sys.executable, CONVERTER, *map(str, args)], capture_output=True, text=True,
                          timeout=120)


def make_folder(root, clips, splits):
    """clips: id -> (joints (T,22,3), [caption lines]); splits: name -> [ids]."""
    os.makedirs(os.path.join(root, "new_joints"))
    os.makedirs(os.path.join(root, "texts"))
    for cid, (joints, lines) in clips.items():
        np.save(os.path.join(root, "new_joints", cid + ".npy"), joints)
        with open(os.path.join(root, "texts", cid + ".txt"), "w", encoding="utf-8") as f:
            f.write("\n".join(lines) + "\n")
    for name, ids in splits.items():
        with open(os.path.join(root, name + ".txt"), "w") as f:
            f.write("\n".join(ids) + "\n")


class MiniatureRoundTrip(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="hml3d_")
        cls.root = os.path.join(cls.tmp, "HumanML3D")
        rng = np.random.default_rng(7)

        def joints(t):
            return rng.normal(0.0, 0.5, size=(t, 22, 3)).astype(np.float32)

        cls.clips = {
            "000001": (joints(60), ["A man walks forward.#a/DET man/NOUN walk/VERB#0.0#0.0",
                                    "someone strolls, slowly#someone/PRON#0.0#0.0"]),
            # longer than 196: cropped; its sub-span 1.0-4.0 s (frames 20..80) becomes its own clip
            "000002": (joints(250), ["a person jumps twice#x#0.0#0.0",
                                     "the person jumps#x#1.0#4.0"]),
            "000003": (joints(30), ["too short to keep#x#0.0#0.0"]),
            # sub-span of 20 frames is shorter than min-len: dropped
            "000004": (joints(120), ["a person kicks#x#0.0#0.0", "kick#x#0.5#1.5"]),
            "M000001": (joints(60), ["A man walks forward.#x#0.0#0.0"]),
            "000005": (joints(45), ["A person sits down#x#0.0#0.0"]),
            "000006": (joints(100), ["waving the right hand#x#nan#nan"]),
        }
        cls.splits = {"train": ["000001", "000002", "M000001"], "val": ["000003", "000004"],
                      "test": ["000005", "000006"]}
        make_folder(cls.root, cls.clips, cls.splits)
        cls.out = os.path.join(cls.tmp, "mini.h5")
        cls.result = run_converter(cls.root, cls.out)

    @classmethod
    def tearDownClass(cls):
        shutil.rmtree(cls.tmp, ignore_errors=True)

    def expected(self):
        """(id, split, frames, captions) in the order the converter must write them."""
        c = self.clips
        return [
            ("000001", "train", c["000001"][0], ["A man walks forward.", "someone strolls, slowly"]),
            ("000002", "train", c["000002"][0][:196], ["a person jumps twice"]),
            ("000002#1.0_4.0", "train", c["000002"][0][20:80], ["the person jumps"]),
            ("M000001", "train", c["M000001"][0], ["A man walks forward."]),
            ("000004", "val", c["000004"][0], ["a person kicks"]),
            ("000005", "test", c["000005"][0], ["A person sits down"]),
            ("000006", "test", c["000006"][0], ["waving the right hand"]),
        ]

    def test_exit_code_and_report(self):
        self.assertEqual(self.result.returncode, 0, self.result.stderr)
        self.assertIn("skipped 1 clips shorter than 40", self.result.stdout)
        self.assertIn("1 added, 1 dropped", self.result.stdout)

    def test_clips_lengths_joints_captions(self):
        m = motionio.read_motion(self.out)
        exp = self.expected()
        self.assertEqual(m.ids, [e[0] for e in exp])
        self.assertEqual(m.split, [e[1] for e in exp])
        self.assertEqual(m.lengths.tolist(), [len(e[2]) for e in exp])
        self.assertEqual(m.lengths.dtype, np.int32)
        self.assertEqual(m.joints.shape, (len(exp), 196, 22, 3))
        self.assertEqual(m.joints.dtype, np.float32)
        for i, (_, _, frames, caps) in enumerate(exp):
            np.testing.assert_array_equal(m.joints[i, :len(frames)], frames)
            self.assertFalse(m.joints[i, len(frames):].any(), "padding must be zero")
            self.assertEqual(m.captions[i], caps)
        self.assertNotIn("000003", m.ids)
        self.assertFalse(any(i.startswith("000004#") for i in m.ids))
        self.assertEqual(m.fps, 20.0)
        self.assertIsNone(m.labels)

    def test_stats_vocab_provenance_skeleton(self):
        m = motionio.read_motion(self.out)
        train = np.concatenate([e[2] for e in self.expected() if e[1] == "train"]).reshape(-1, 3)
        train = train.astype(np.float64)
        np.testing.assert_allclose(m.stats["joint_mean"], train.mean(axis=0), rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(m.stats["joint_std"], np.maximum(train.std(axis=0), 1e-4), rtol=1e-5, atol=1e-6)
        self.assertEqual(m.stats["feature_layout"], "none")
        self.assertNotIn("feature_mean", m.stats)
        # The C++ vocabulary format: specials, then words by frequency, ties alphabetical.
        counts = {}
        for e in self.expected():
            if e[1] == "train":
                for c in e[3]:
                    for w in re.findall(r"[a-z]+", c.lower()):
                        counts[w] = counts.get(w, 0) + 1
        words = sorted(counts, key=lambda w: (-counts[w], w))
        self.assertEqual(m.vocab, ["<pad>", "<unk>", "<sos>", "<eos>"] + words)
        self.assertEqual(counts[m.vocab[4]], max(counts.values()))
        self.assertEqual(m.provenance["generator"], "humanml3d_to_h5.py")
        self.assertEqual(m.provenance["seed"], 0)
        self.assertIn("humanml3d_to_h5.py", m.provenance["config"])
        self.assertRegex(m.provenance["created"], r"^\d{4}-\d\d-\d\dT\d\d:\d\d:\d\dZ$")
        default = motionio.humanml3d_skeleton()
        self.assertEqual(m.skeleton["names"], default["names"])
        np.testing.assert_array_equal(m.skeleton["parents"], default["parents"])
        np.testing.assert_array_equal(m.skeleton["bone_lengths"], default["bone_lengths"])
        self.assertEqual(m.skeleton["roles"]["toes"], [10, 11])
        self.assertEqual(m.skeleton["roles"]["face"], [2, 1, 17, 16])
        self.assertEqual(m.skeleton["chains"][0], [0, 2, 5, 8, 11])

    def test_options(self):
        out = os.path.join(self.tmp, "options.h5")
        r = run_converter(self.root, out, "--no-mirror", "--limit", "2", "--splits", "train,test",
                          "--max-len", "100")
        self.assertEqual(r.returncode, 0, r.stderr)
        m = motionio.read_motion(out)
        self.assertEqual(m.ids, ["000001", "000002", "000002#1.0_4.0", "000005", "000006"])
        self.assertEqual(m.lengths.tolist(), [60, 100, 60, 45, 100])
        self.assertEqual(m.t_max, 100)

    def test_no_train_split_means_no_stats(self):
        out = os.path.join(self.tmp, "test_only.h5")
        r = run_converter(self.root, out, "--splits", "test")
        self.assertEqual(r.returncode, 0, r.stderr)
        m = motionio.read_motion(out)
        self.assertIsNone(m.stats)
        self.assertIsNone(m.vocab)


class BadInput(unittest.TestCase):
    def setUp(self):
        self.tmp = tempfile.mkdtemp(prefix="hml3d_bad_")
        self.root = os.path.join(self.tmp, "HumanML3D")
        frames = np.zeros((50, 22, 3), np.float32)
        make_folder(self.root, {"000001": (frames, ["a#b#0.0#0.0"])},
                    {"train": ["000001"], "val": [], "test": []})
        self.out = os.path.join(self.tmp, "out.h5")

    def tearDown(self):
        shutil.rmtree(self.tmp, ignore_errors=True)

    def assert_fails_naming(self, path, *args):
        r = run_converter(self.root, self.out, *args)
        self.assertEqual(r.returncode, 2, r.stdout + r.stderr)
        self.assertIn(path, r.stderr)
        self.assertNotIn("Traceback", r.stderr)
        self.assertEqual(os.listdir(self.tmp), ["HumanML3D"], "no output (or temp) file may be left")

    def test_missing_new_joints(self):
        shutil.rmtree(os.path.join(self.root, "new_joints"))
        self.assert_fails_naming(os.path.join(self.root, "new_joints"))

    def test_missing_split_file(self):
        os.remove(os.path.join(self.root, "val.txt"))
        self.assert_fails_naming(os.path.join(self.root, "val.txt"))

    def test_missing_clip_file(self):
        os.remove(os.path.join(self.root, "new_joints", "000001.npy"))
        self.assert_fails_naming(os.path.join(self.root, "new_joints", "000001.npy"))

    def test_wrong_shape(self):
        np.save(os.path.join(self.root, "new_joints", "000001.npy"), np.zeros((50, 263), np.float32))
        self.assert_fails_naming(os.path.join(self.root, "new_joints", "000001.npy"))

    def test_missing_root(self):
        self.root = os.path.join(self.tmp, "nope")
        r = run_converter(self.root, self.out)
        self.assertEqual(r.returncode, 2)
        self.assertIn(self.root, r.stderr)


@unittest.skipUnless(os.path.isfile(REAL_CLIP), "shared/reference/humanml3d is absent")
class RealClip(unittest.TestCase):
    """The reference clip checks the built-in skeleton and HumanML3D's conventions."""

    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="hml3d_real_")
        root = os.path.join(cls.tmp, "HumanML3D")
        cls.source = np.load(REAL_CLIP)
        make_folder(root, {"012314": (cls.source, ["a person walks and turns#x#0.0#0.0"])},
                    {"train": ["012314"], "val": [], "test": []})
        cls.out = os.path.join(cls.tmp, "real.h5")
        cls.result = run_converter(root, cls.out)

    @classmethod
    def tearDownClass(cls):
        shutil.rmtree(cls.tmp, ignore_errors=True)

    def test_converted_exactly(self):
        self.assertEqual(self.result.returncode, 0, self.result.stderr)
        m = motionio.read_motion(self.out)
        self.assertEqual(m.lengths.tolist(), [len(self.source)])
        np.testing.assert_array_equal(m.clip(0), self.source)

    def test_bone_lengths_match_skeleton_every_frame(self):
        m = motionio.read_motion(self.out)
        clip, parents = m.clip(0).astype(np.float64), m.skeleton["parents"]
        bones = np.linalg.norm(clip[:, 1:] - clip[:, parents[1:]], axis=-1)  # [T, J-1]
        err = np.abs(bones - m.skeleton["bone_lengths"][None, 1:])
        self.assertLess(err.max(), 1e-3, f"worst bone {m.skeleton['names'][1 + err.max(0).argmax()]}")

    def test_floor_origin_and_facing(self):
        m = motionio.read_motion(self.out)
        clip, names = m.clip(0), m.skeleton["names"]
        j = {n: i for i, n in enumerate(names)}
        self.assertAlmostEqual(float(clip[..., 1].min()), 0.0, delta=0.02)  # floor at y = 0
        np.testing.assert_allclose(clip[0, 0, [0, 2]], [0.0, 0.0], atol=0.02)  # root starts at xz origin
        self.assertGreater(clip[0, j["head"], 1], clip[0, j["pelvis"], 1] + 0.3)  # Y up
        # Left at +X and forward +Z at frame 0: forward = up x (right - left).
        across = (clip[0, j["r_hip"]] - clip[0, j["l_hip"]]) + (clip[0, j["r_shoulder"]] - clip[0, j["l_shoulder"]])
        forward = np.cross([0.0, 1.0, 0.0], across)
        forward /= np.linalg.norm(forward)
        self.assertGreater(forward[2], 0.7)
        self.assertLess(across[0], 0.0)


class SkeletonYamlAgreement(unittest.TestCase):
    def test_builtin_yaml_parses_back(self):
        default = motionio.humanml3d_skeleton()
        parsed = motionio.skeleton_from_yaml_text(default["yaml"], "built-in")
        self.assertEqual(parsed["names"], default["names"])
        np.testing.assert_array_equal(parsed["rest_directions"], default["rest_directions"])
        np.testing.assert_array_equal(parsed["bone_lengths"], default["bone_lengths"])
        self.assertEqual(parsed["roles"], motionio.HUMANML3D22_ROLES)
        self.assertEqual(parsed["chains"], motionio.HUMANML3D22_CHAINS)

    @unittest.skipUnless(os.path.isfile(os.path.join(REPO, "configs", "skeletons", "humanml3d22.yaml")),
                         "configs/skeletons/humanml3d22.yaml not in this tree yet")
    def test_repo_yaml_matches_builtin(self):
        repo = motionio.load_skeleton_yaml(os.path.join(REPO, "configs", "skeletons", "humanml3d22.yaml"))
        default = motionio.humanml3d_skeleton()
        self.assertEqual(repo["names"], default["names"])
        np.testing.assert_array_equal(repo["parents"], default["parents"])
        np.testing.assert_allclose(repo["rest_directions"], default["rest_directions"], atol=1e-9)
        np.testing.assert_allclose(repo["bone_lengths"], default["bone_lengths"], atol=1e-4)
        for role, joints in motionio.HUMANML3D22_ROLES.items():
            self.assertEqual(repo["roles"].get(role), joints, f"role {role}")


if __name__ == "__main__":
    unittest.main()
