"""Tests for tools/motionio.py: exact round trips, the validation rules of docs/formats.md
(each broken file raises MotionFileError naming the dataset), atomic writes, YAML subset."""

import os
import shutil
import tempfile
import unittest

from tools_test_util import require_modules

require_modules("numpy", "h5py")
import numpy as np  # noqa: E402
import h5py  # noqa: E402
import motionio  # noqa: E402
from motionio import MotionFileError  # noqa: E402


def sample_data(rng, n=3, t_max=12):
    lengths = np.array([12, 5, 9][:n], dtype=np.int32)
    joints = rng.normal(size=(n, t_max, 22, 3)).astype(np.float32)
    for i, length in enumerate(lengths):
        joints[i, length:] = 0.0
    return dict(joints=joints, lengths=lengths, ids=["a", "b#1.0_2.0", "ç"][:n],
                split=["train", "val", "sample"][:n],
                captions=[["café au lait", "two"], ["one"], ["x", "y", "z"]][:n])


class RoundTrip(unittest.TestCase):
    def setUp(self):
        self.tmp = tempfile.mkdtemp(prefix="motionio_")
        self.rng = np.random.default_rng(1)

    def tearDown(self):
        shutil.rmtree(self.tmp, ignore_errors=True)

    def test_array_and_streamed_writes_agree(self):
        d = sample_data(self.rng)
        a, b = os.path.join(self.tmp, "a.h5"), os.path.join(self.tmp, "b.h5")
        stats = {"joint_mean": [0.1, 0.2, 0.3], "joint_std": [1, 2, 3], "feature_mean": np.arange(5),
                 "feature_std": np.ones(5), "feature_layout": "mc67"}
        motionio.write_motion(a, **d, labels=["p", "q", "r"], stats=stats, vocab=list(motionio.VOCAB_SPECIALS) + ["au", "café"], fps=30.0,
                              provenance={"generator": "g", "version": "v", "seed": 5, "config": "c: 1",
                                          "created": "2024-01-01T00:00:00Z"})
        clips = [d["joints"][i, :d["lengths"][i]] for i in range(3)]
        motionio.write_motion(b, clips, d["lengths"], d["ids"], d["split"], d["captions"])
        ma, mb = motionio.read_motion(a), motionio.read_motion(b)
        for m in (ma, mb):
            np.testing.assert_array_equal(m.joints, d["joints"])
            self.assertEqual(m.lengths.tolist(), d["lengths"].tolist())
            self.assertEqual(m.ids, d["ids"])
            self.assertEqual(m.split, d["split"])
            self.assertEqual(m.captions, d["captions"])
            self.assertEqual(m.skeleton["names"], motionio.HUMANML3D22_NAMES)
        self.assertEqual(ma.fps, 30.0)
        self.assertEqual(ma.labels, ["p", "q", "r"])
        self.assertIsNone(mb.labels)
        self.assertEqual(ma.vocab, list(motionio.VOCAB_SPECIALS) + ["au", "café"])
        self.assertEqual(ma.stats["feature_layout"], "mc67")
        np.testing.assert_array_equal(ma.stats["feature_mean"], np.arange(5, dtype=np.float32))
        self.assertEqual(ma.provenance["seed"], 5)
        self.assertEqual(ma.provenance["config"], "c: 1")
        self.assertEqual(mb.provenance["generator"], "")
        self.assertIsNone(mb.stats)

    def test_documented_layout(self):
        path = os.path.join(self.tmp, "layout.h5")
        motionio.write_motion(path, **sample_data(self.rng), vocab=list(motionio.VOCAB_SPECIALS) + ["w"],
                              stats={"joint_mean": [0, 0, 0], "joint_std": [1, 1, 1]})
        with h5py.File(path, "r") as f:
            self.assertEqual(f.attrs["format"], "motionctl.motion")
            self.assertEqual(int(f.attrs["format_version"]), 1)
            self.assertEqual(float(f.attrs["fps"]), 20.0)
            self.assertEqual(f["joints"].dtype, np.float32)
            self.assertEqual(f["joints"].compression, "gzip")
            self.assertIsNotNone(f["joints"].chunks)
            self.assertEqual(f["lengths"].dtype, np.int32)
            self.assertEqual(f["captions/offsets"].dtype, np.int64)
            self.assertEqual(f["captions/offsets"][:].tolist(), [0, 2, 3, 6])
            for key in ("ids", "split", "captions/text", "skeleton/names", "vocab"):
                info = h5py.check_string_dtype(f[key].dtype)
                self.assertEqual((info.encoding, info.length), ("utf-8", None), key)
            self.assertEqual(f["skeleton/parents"].dtype, np.int32)
            self.assertEqual(f["skeleton/rest_directions"].dtype, np.float64)
            self.assertEqual(f["skeleton/bone_lengths"].dtype, np.float64)
            self.assertEqual(f["skeleton"].attrs["name"], "humanml3d22")
            self.assertIn("roles:", f["skeleton"].attrs["yaml"])
            self.assertEqual(f["stats/joint_mean"].dtype, np.float32)
            self.assertEqual(f["stats"].attrs["feature_layout"], "none")
            self.assertEqual(f["provenance"].attrs["seed"].dtype, np.int64)


class Validation(unittest.TestCase):
    """Each case breaks one rule of docs/formats.md in an otherwise valid file."""

    def setUp(self):
        self.tmp = tempfile.mkdtemp(prefix="motionio_bad_")
        self.path = os.path.join(self.tmp, "m.h5")
        motionio.write_motion(self.path, **sample_data(np.random.default_rng(2)))

    def tearDown(self):
        shutil.rmtree(self.tmp, ignore_errors=True)

    def broken(self, edit, *expected_words):
        with h5py.File(self.path, "a") as f:
            edit(f)
        motionio.seal_h5_file(self.path)  # edited in place on purpose: re-seal
        with self.assertRaises(MotionFileError) as ctx:
            motionio.read_motion(self.path)
        msg = str(ctx.exception)
        self.assertIn(self.path, msg)
        for word in expected_words:
            self.assertIn(word, msg)

    def replace(self, f, key, data, **kw):
        del f[key]
        f.create_dataset(key, data=data, **kw)

    def test_format_attr(self):
        self.broken(lambda f: f.attrs.__setitem__("format", "other"), "format")

    def test_version(self):
        self.broken(lambda f: f.attrs.__setitem__("format_version", 2), "format_version")

    def test_missing_dataset(self):
        self.broken(lambda f: f.__delitem__("lengths"), "'lengths'")

    def test_joint_count_mismatch(self):
        self.broken(lambda f: self.replace(f, "joints", np.zeros((3, 12, 21, 3), np.float32)), "'joints'", "22")

    def test_non_finite(self):
        def edit(f):
            f["joints"][1, 0, 0, 0] = np.nan
        self.broken(edit, "non-finite", "clip 1")

    def test_length_out_of_range(self):
        self.broken(lambda f: self.replace(f, "lengths", np.array([12, 13, 9], np.int32)), "'lengths'")
        with h5py.File(self.path, "a") as f:
            self.replace(f, "lengths", np.array([12, 0, 9], np.int32))
        motionio.seal_h5_file(self.path)  # edited in place on purpose: re-seal
        self.assertRaises(MotionFileError, motionio.read_motion, self.path)

    def test_ids_unique(self):
        self.broken(lambda f: self.replace(f, "ids", ["a", "a", "c"], dtype=motionio.STR_DTYPE), "'ids'")

    def test_clip_without_caption(self):
        self.broken(lambda f: self.replace(f, "captions/offsets", np.array([0, 3, 3, 6], np.int64)),
                    "no caption")

    def test_wrong_count(self):
        self.broken(lambda f: self.replace(f, "split", ["train", "val"], dtype=motionio.STR_DTYPE), "'split'")

    def test_other_writers_scalar_styles_accepted(self):
        # C++ HDF5 wrappers may write scalars as 1-element arrays or fixed-length strings.
        with h5py.File(self.path, "a") as f:
            f.attrs["fps"] = np.array([25.0])
            f.attrs["format_version"] = np.array([1], np.int32)
            f.attrs["format"] = np.bytes_(b"motionctl.motion")
            f["provenance"].attrs["seed"] = np.array([7], np.int64)
        motionio.seal_h5_file(self.path)  # edited in place on purpose: re-seal
        m = motionio.read_motion(self.path)
        self.assertEqual((m.fps, m.provenance["seed"]), (25.0, 7))

    def test_yaml_attr_disagreeing_with_datasets(self):
        other = motionio.humanml3d_skeleton()["yaml"].replace("l_hip", "left_hip")
        self.broken(lambda f: f["skeleton"].attrs.__setitem__("yaml", other), "yaml")

    def test_not_hdf5_and_missing(self):
        with open(self.path, "w") as f:
            f.write("not hdf5")
        self.assertRaisesRegex(MotionFileError, "not an HDF5 file", motionio.read_motion, self.path)
        self.assertRaisesRegex(MotionFileError, "no such file", motionio.read_motion, self.path + ".x")


def read_bytes(path):
    with open(path, "rb") as f:
        return f.read()


class AtomicWrite(unittest.TestCase):
    def test_failed_write_leaves_nothing(self):
        tmp = tempfile.mkdtemp(prefix="motionio_atomic_")
        try:
            d = sample_data(np.random.default_rng(3))
            path = os.path.join(tmp, "m.h5")
            bad_clips = [d["joints"][0], d["joints"][1][:, :21]]  # second clip has the wrong joint count
            with self.assertRaises(MotionFileError):
                motionio.write_motion(path, bad_clips + [d["joints"][2]], d["lengths"], d["ids"], d["split"],
                                      d["captions"])
            with self.assertRaises(MotionFileError):
                motionio.write_motion(path, d["joints"], d["lengths"], d["ids"][:2], d["split"], d["captions"])
            self.assertEqual(os.listdir(tmp), [])
            # An existing file survives a failed overwrite untouched.
            motionio.write_motion(path, **d)
            before = read_bytes(path)
            d["joints"][0, 0, 0, 0] = np.inf
            with self.assertRaises(MotionFileError):
                motionio.write_motion(path, **d)
            self.assertEqual(read_bytes(path), before)
            self.assertEqual(os.listdir(tmp), ["m.h5"])
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


class Seal(unittest.TestCase):
    """The checksum seal in the user block (docs/formats.md): any changed byte is refused."""

    def test_changed_byte_truncation_and_unsealed(self):
        tmp = tempfile.mkdtemp(prefix="motionio_seal_")
        try:
            path = os.path.join(tmp, "m.h5")
            motionio.write_motion(path, **sample_data(np.random.default_rng(4)))
            good = read_bytes(path)
            self.assertTrue(good.startswith(motionio.SEAL_MAGIC))
            self.assertTrue(motionio.check_h5_seal(path))
            for pos in (600, len(good) // 2, len(good) - 1):
                bad = bytearray(good)
                bad[pos] ^= 0x20
                with open(path, "wb") as f:
                    f.write(bad)
                self.assertRaisesRegex(MotionFileError, "damaged", motionio.read_motion, path)
            with open(path, "wb") as f:
                f.write(good[:-5])
            self.assertRaisesRegex(MotionFileError, "truncated", motionio.read_motion, path)
            with open(path, "wb") as f:  # no seal: read as an older file
                f.write(bytes(motionio.SEAL_BLOCK) + good[motionio.SEAL_BLOCK:])
            self.assertFalse(motionio.check_h5_seal(path))
            self.assertEqual(len(motionio.read_motion(path).ids), 3)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


class YamlSubset(unittest.TestCase):
    def test_block_and_flow_styles(self):
        text = (
            "# a two-joint skeleton\n"
            "name: 'tiny'   # quoted\n"
            "joints:\n"
            "  - {name: root, parent: -1, direction: [0, 0, 0], length: 0.0}\n"
            "  - name: tip\n"
            "    parent: 0\n"
            "    direction: [0, 1.0, 0]\n"
            "    length: 0.5\n"
            "chains:\n"
            "  - [0, 1]\n"
            "roles:\n"
            "  top: [1]\n"
            "  all: [0, 1]\n")
        s = motionio.skeleton_from_yaml_text(text, "tiny.yaml")
        self.assertEqual(s["name"], "tiny")
        self.assertEqual(s["names"], ["root", "tip"])
        self.assertEqual(s["parents"].tolist(), [-1, 0])
        self.assertEqual(s["bone_lengths"].tolist(), [0.0, 0.5])
        self.assertEqual(s["chains"], [[0, 1]])
        self.assertEqual(s["roles"], {"top": [1], "all": [0, 1]})
        self.assertEqual(s["yaml"], text)

    def test_errors_name_the_file(self):
        cases = [
            "name: x\njoints: [\n",                                           # unterminated flow
            "name: x\n",                                                      # no joints
            "joints:\n  - {name: a, parent: -1, direction: [0, 0], length: 0}\n",  # 2-d direction
            "joints:\n  - {name: a, parent: 0, direction: [0, 0, 0], length: 0}\n",  # root parent
            "joints:\n  - {name: a, parent: -1, direction: [0, 0, 0], length: 0}\n"
            "  - {name: b, parent: 0, direction: [0, 2, 0], length: 1}\n",   # not unit
        ]
        for text in cases:
            with self.assertRaises(MotionFileError, msg=text) as ctx:
                motionio.skeleton_from_yaml_text(text, "bad.yaml")
            self.assertIn("bad.yaml", str(ctx.exception))

    def test_load_missing_file(self):
        self.assertRaisesRegex(MotionFileError, "nope.yaml", motionio.load_skeleton_yaml, "/nonexistent/nope.yaml")


if __name__ == "__main__":
    unittest.main()
