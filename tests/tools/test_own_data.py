"""Your own data end to end (issue 17): a miniature HumanML3D folder (clips with mirrored and
rotated copies and span captions, made from fixture motion) goes through tools/humanml3d_to_h5.py,
then the binary runs on the converted file with no fixture: `train` (flow prior and evaluator, a
few steps), `sample`, `generate`, `eval` and `export`. The real HumanML3D clip in
../shared/reference/humanml3d joins the test split when it is present (skipped cleanly when not).
These are the README's "Train on your own data" commands."""

import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import unittest

from tools_test_util import BINARY, REPO, TOOLS, require_binary, require_modules

require_modules("numpy", "h5py")
import numpy as np  # noqa: E402
import h5py  # noqa: E402

REAL_CLIP = os.path.join(REPO, "..", "shared", "reference", "humanml3d", "012314_new_joints.npy")
import motionio  # noqa: E402

require_binary()

# HumanML3D's mirror (its motion_representation.ipynb): negate x, swap left and right joints.
MIRROR = [0, 2, 1, 3, 5, 4, 6, 8, 7, 9, 11, 10, 12, 14, 13, 15, 17, 16, 19, 18, 21, 20]
STEPS = 30  # training steps of the prior and the evaluator: enough to run every code path


def run(*args, timeout=900):
    env = dict(os.environ, OMP_NUM_THREADS="1", CI="1")
    r = subprocess.run([BINARY, *map(str, args)], cwd=REPO, capture_output=True, text=True, timeout=timeout,
                       env=env)
    return r


def mirror(joints):
    out = joints[:, MIRROR].copy()
    out[..., 0] *= -1
    return out


def mirror_caption(text):
    swap = {"left": "right", "right": "left"}
    return re.sub(r"\b(left|right)\b", lambda m: swap[m.group(1)], text)


def rotate(joints, angle, shift):
    """Turned about +Y by `angle` and moved by (shift[0], 0, shift[1]): a clip that starts neither at the
    origin nor facing +Z, unlike HumanML3D's own clips."""
    c, s = math.cos(angle), math.sin(angle)
    r = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    out = joints @ r.T
    out[..., 0] += shift[0]
    out[..., 2] += shift[1]
    return out.astype(np.float32)


def write_clip(root, cid, joints, lines):
    np.save(os.path.join(root, "new_joints", cid + ".npy"), joints.astype(np.float32))
    with open(os.path.join(root, "texts", cid + ".txt"), "w", encoding="utf-8") as f:
        f.write("\n".join(lines) + "\n")


def caption_line(text, start=0.0, end=0.0):
    tokens = " ".join(f"{w}/X" for w in text.lower().split())
    return f"{text}#{tokens}#{start}#{end}"


class OwnDataEndToEnd(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="own_data_")
        cls.runs = os.path.join(cls.tmp, "runs")
        fx = os.path.join(cls.tmp, "fx.h5")
        r = run("fixture", "configs/data/smoke.yaml", f"output={fx}", "fixture.num_clips=40")
        assert r.returncode == 0, r.stdout + r.stderr
        source = motionio.read_motion(fx)

        root = cls.root = os.path.join(cls.tmp, "HumanML3D")
        os.makedirs(os.path.join(root, "new_joints"))
        os.makedirs(os.path.join(root, "texts"))
        splits = {"train": [], "val": [], "test": []}
        cls.span_ids = []
        for i in range(source.num_clips):
            clip, caps, split = source.clip(i), source.captions[i], source.split[i]
            cid = f"{i:06d}"
            lines = [caption_line(c) for c in caps]
            if len(clip) >= 100:  # a span caption: frames 0..50 become their own clip
                lines.append(caption_line("the first part of the motion", 0.0, 2.5))
                cls.span_ids.append(f"{cid}#0.0_2.5")
            write_clip(root, cid, clip, lines)
            write_clip(root, "M" + cid, mirror(clip), [caption_line(mirror_caption(c)) for c in caps])
            splits[split] += [cid, "M" + cid]
            if i % 3 == 0:
                rid = f"{cid}r"
                write_clip(root, rid, rotate(clip, 0.4 * i + 0.7, (1.5, -2.0)), [caption_line(c) for c in caps])
                splits[split].append(rid)
        cls.real = os.path.isfile(REAL_CLIP)
        if cls.real:
            real = np.load(REAL_CLIP)
            text = "a person walks forward and turns around"
            write_clip(root, "012314", real, [caption_line(text)])
            write_clip(root, "M012314", mirror(real), [caption_line(text)])
            write_clip(root, "012314r", rotate(real, 2.0, (0.5, 3.0)), [caption_line(text)])
            # First in the test split, so sample, generate and eval all use it.
            splits["test"] = ["012314", "M012314", "012314r"] + splits["test"]
        for name, ids in splits.items():
            with open(os.path.join(root, name + ".txt"), "w") as f:
                f.write("\n".join(ids) + "\n")

        cls.data = os.path.join(cls.tmp, "mine.h5")
        cls.convert = subprocess.run([sys.executable, os.path.join(TOOLS, "humanml3d_to_h5.py"), root, cls.data],
                                     capture_output=True, text=True, timeout=300)
        assert cls.convert.returncode == 0, cls.convert.stdout + cls.convert.stderr
        cls.prior = run("train", "configs/prior/flow_tiny.yaml", f"data.path={cls.data}", "data.fixture=''",
                        f"run.root={cls.runs}", "run.name=mine", f"optim.steps={STEPS}", "optim.warmup=5", "optim.batch_size=8",
                        "run.log_every=10", "run.checkpoint_every=10", "run.threads=1")
        cls.prior_dir = os.path.join(cls.runs, "prior", "mine")
        cls.samples = os.path.join(cls.tmp, "samples.h5")
        cls.sample = run("sample", "configs/sample/t2m_smoke.yaml", f"prior.run_dir={cls.prior_dir}",
                         f"texts.data={cls.data}", "texts.num_samples=4", "sampler.steps=8", "run.threads=1",
                         f"output={cls.samples}")
        cls.generated = os.path.join(cls.tmp, "keyframes.h5")
        cls.generate = run("generate", "configs/control/keyframes_smoke.yaml",
                           f"generator.prior.run_dir={cls.prior_dir}", f"data.path={cls.data}", "data.fixture=''",
                           "data.num_samples=4", "generator.sampler.steps=8", "run.threads=1",
                           f"run.root={cls.runs}", f"output={cls.generated}")
        cls.eval = run("eval", "configs/eval/t2m_smoke.yaml", f"eval.reference={cls.data}",
                       f"eval.motions={cls.samples}", f"run.root={cls.runs}",
                       f"eval.evaluator_overrides=[data.path={cls.data}, run.name=mine, optim.steps={STEPS}, optim.batch_size=8, "
                       "optim.warmup=5, run.log_every=10, run.checkpoint_every=10]",
                       "protocol.repeats=2", "protocol.r_precision_pool=4", "protocol.diversity_pairs=4",
                       "run.threads=1")
        cls.bvh_dir = os.path.join(cls.tmp, "bvh")
        cls.export = run("export", "--format", "bvh", cls.generated, "--out", cls.bvh_dir)

    @classmethod
    def tearDownClass(cls):
        shutil.rmtree(cls.tmp, ignore_errors=True)

    def test_converted_file_has_the_one_vocabulary_and_joint_statistics(self):
        m = motionio.read_motion(self.data)
        self.assertEqual(m.vocab[:4], list(motionio.VOCAB_SPECIALS))
        train = [m.captions[i] for i in m.indices_of_split("train")]
        self.assertEqual(m.vocab, motionio.build_vocab(c for cs in train for c in cs))
        self.assertEqual(m.stats["feature_layout"], "none")
        moments = motionio.JointMoments()
        for i in m.indices_of_split("train"):
            moments.add(m.clip(i))
        np.testing.assert_allclose(m.stats["joint_std"], moments.stats()["joint_std"], rtol=1e-6)
        for sid in self.span_ids:
            self.assertIn(sid, m.ids)
        self.assertTrue(any(i.startswith("M") for i in m.ids))
        self.assertTrue(any(i.endswith("r") for i in m.ids))
        if self.real:
            self.assertEqual(m.ids[m.indices_of_split("test")[0]], "012314")

    def test_train_without_fixture(self):
        self.assertEqual(self.prior.returncode, 0, self.prior.stdout + self.prior.stderr)
        self.assertTrue(os.path.isfile(os.path.join(self.prior_dir, "DONE")))
        self.assertFalse(os.path.exists(os.path.join(REPO, "data", "mine.h5")))
        with open(os.path.join(self.prior_dir, "config.yaml")) as f:
            self.assertIn(self.data, f.read())

    def test_sample(self):
        self.assertEqual(self.sample.returncode, 0, self.sample.stdout + self.sample.stderr)
        m = motionio.read_motion(self.samples)
        self.assertEqual(m.num_clips, 4)
        self.assertTrue(np.isfinite(m.joints).all())
        data = motionio.read_motion(self.data)
        test = data.indices_of_split("test")[:4]
        self.assertEqual(m.ids, [data.ids[i] for i in test])
        self.assertEqual([c[0] for c in m.captions], [data.captions[i][0] for i in test])

    def test_generate(self):
        out = self.generate.stdout + self.generate.stderr
        self.assertEqual(self.generate.returncode, 0, out)
        self.assertRegex(out, r"max hard residual [0-9.e+-]+")
        residual = float(re.search(r"max hard residual ([0-9.e+-]+)", out).group(1))
        self.assertLess(residual, 1e-3)  # ProjFlow's hard keyframes hold on the converted data too
        m = motionio.read_motion(self.generated)
        self.assertEqual(m.num_clips, 4)
        with h5py.File(self.generated, "r") as f:
            self.assertIn("control", f)

    def test_eval(self):
        out = self.eval.stdout + self.eval.stderr
        self.assertEqual(self.eval.returncode, 0, out)
        for metric in ("fid", "r_precision_top3", "diversity"):
            self.assertRegex(out, rf"{metric}\s")
        self.assertTrue(os.path.isfile(os.path.join(self.runs, "evaluator", "mine", "DONE")))

    def test_export_generated_samples_to_bvh(self):
        self.assertEqual(self.export.returncode, 0, self.export.stdout + self.export.stderr)
        errors = [float(x) for x in re.findall(r"re-read error ([0-9.e+-]+) m", self.export.stdout)]
        self.assertEqual(len(errors), 4)
        self.assertLess(max(errors), 1e-4)
        self.assertEqual(len([n for n in os.listdir(self.bvh_dir) if n.endswith(".bvh")]), 4)

    @unittest.skipUnless(os.path.isfile(REAL_CLIP), "../shared/reference/humanml3d is absent")
    def test_real_clip_exports_to_bvh(self):
        out = os.path.join(self.tmp, "bvh_real")
        r = run("export", self.data, "--ids", "012314,012314r", "--out", out)
        self.assertEqual(r.returncode, 0, r.stdout + r.stderr)
        errors = [float(x) for x in re.findall(r"re-read error ([0-9.e+-]+) m", r.stdout)]
        self.assertEqual(len(errors), 2)
        self.assertLess(max(errors), 1e-4)
        print("\nreal clip 012314:", r.stdout.strip().replace("\n", " | "), file=sys.stderr)


class BadOwnData(unittest.TestCase):
    """A file in the old converter's vocabulary layout is refused by name, with the fix; export refuses
    unknown ids and an output path that is a file."""

    def test_export_bad_input(self):
        tmp = tempfile.mkdtemp(prefix="own_data_export_")
        try:
            path = os.path.join(tmp, "m.h5")
            joints = np.zeros((1, 5, 22, 3), np.float32)
            joints[..., 1] = np.linspace(0, 1.7, 22)[None, None, :]
            motionio.write_motion(path, joints, [5], ["only"], ["test"], [["stand"]])
            r = run("export", path, "--out", os.path.join(tmp, "o"), "--ids", "only,ghost")
            self.assertEqual(r.returncode, 2, r.stdout + r.stderr)
            self.assertIn("'ghost'", r.stderr)
            self.assertFalse(os.path.exists(os.path.join(tmp, "o", "0000_only.bvh")))
            blocker = os.path.join(tmp, "file")
            open(blocker, "w").close()
            r = run("export", path, "--out", blocker)
            self.assertEqual(r.returncode, 2, r.stdout + r.stderr)
            self.assertIn(blocker, r.stderr)
            r = run("export", path, "--out", os.path.join(tmp, "o"), "--translations", "some")
            self.assertEqual(r.returncode, 2)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def test_old_vocabulary_layout_is_refused(self):
        tmp = tempfile.mkdtemp(prefix="own_data_bad_")
        try:
            path = os.path.join(tmp, "old.h5")
            joints = np.zeros((2, 40, 22, 3), np.float32)
            joints[:, :, :, 1] = 1.0
            motionio.write_motion(path, joints, [40, 40], ["a", "b"], ["train", "test"], [["walk"], ["run"]],
                                  stats={"joint_mean": [0, 1, 0], "joint_std": [1, 1, 1]},
                                  vocab=list(motionio.VOCAB_SPECIALS) + ["run", "walk"])
            with h5py.File(path, "a") as f:  # what tools/humanml3d_to_h5.py 1.0 wrote: sorted words only
                del f["vocab"]
                f.create_dataset("vocab", data=["run", "walk"], dtype=motionio.STR_DTYPE)
            motionio.seal_h5_file(path)
            r = run("train", "configs/prior/flow_tiny.yaml", f"data.path={path}", "data.fixture=''",
                    f"run.root={tmp}/runs", "optim.steps=1")
            self.assertEqual(r.returncode, 2, r.stdout + r.stderr)
            self.assertIn(path, r.stderr)
            self.assertIn("<pad>", r.stderr)
            self.assertIn("humanml3d_to_h5.py", r.stderr)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    unittest.main()
