"""A trained flow prior run from Python (issue 17): `motionctl export --format weights RUN --probe` on
the shipped priors (flow_tiny: the jointly trained text encoder; flow_standard_kin: a frozen text_clip
encoder behind the text adapter and the kinematic head; flow_standard, the same encoder without the
head, when shipped), then tools/flow_reference.py (numpy only) recomputes the text
vectors, the conditional, unconditional and guided velocities and one Euler step of the C++ probe to
<= 1e-4. Also: the file's layout (every tensor float32 and used by the loader, config hash, vocab,
skeleton), byte-identical re-exports, a changed weight detected, and clear errors for a missing or
reshaped dataset, a damaged file, and runs export refuses (foreign type, unfinished, missing)."""

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
import motionio  # noqa: E402
import flow_reference  # noqa: E402
from flow_reference import FlowReference, FlowWeightsError  # noqa: E402

require_binary()

TOLERANCE = 1e-4


def shipped(prefix):
    """The shipped run pretrained/prior/<prefix>-<hash>, or None."""
    root = os.path.join(REPO, "pretrained", "prior")
    names = sorted(n for n in os.listdir(root) if re.fullmatch(prefix + r"-[0-9a-f]{12}", n)) \
        if os.path.isdir(root) else []
    return os.path.join(root, names[0]) if names else None


def run(*args):
    env = dict(os.environ, OMP_NUM_THREADS="1", CI="1")
    return subprocess.run([BINARY, *map(str, args)], cwd=REPO, capture_output=True, text=True, timeout=600, env=env)


def reference(*args):
    return subprocess.run([sys.executable, os.path.join(TOOLS, "flow_reference.py"), *map(str, args)], cwd=REPO,
                          capture_output=True, text=True, timeout=600)


class ExportAndReference(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="flow_ref_")
        cls.files = {}
        for prefix in ("flow_tiny", "flow_standard", "flow_standard_kin"):
            run_dir = shipped(prefix)
            if run_dir is None:
                continue
            out = os.path.join(cls.tmp, prefix + ".h5")
            r = run("export", "--format", "weights", run_dir, "--out", out, "--probe")
            assert r.returncode == 0, r.stdout + r.stderr
            cls.files[prefix] = (run_dir, out)
        assert "flow_tiny" in cls.files, "pretrained/prior/flow_tiny-<hash> is shipped with the repository"

    @classmethod
    def tearDownClass(cls):
        shutil.rmtree(cls.tmp, ignore_errors=True)

    def copy(self, name="flow_tiny"):
        dst = os.path.join(self.tmp, f"copy_{self._testMethodName}.h5")
        shutil.copyfile(self.files[name][1], dst)
        return dst

    # ---------------------------------------------------------------- numbers

    def test_numpy_matches_cpp_on_the_probe(self):
        for name, (run_dir, path) in self.files.items():
            with self.subTest(prior=name):
                diffs = FlowReference(path).check_probe()
                print(f"{name}: " + ", ".join(f"{k} {v:.2e}" for k, v in diffs.items()))
                self.assertEqual(set(diffs), {"text", "null_text", "v_cond", "v_uncond", "v_cfg", "x_next"})
                for k, v in diffs.items():
                    self.assertLessEqual(v, TOLERANCE, f"{name}: {k}")
                # The velocities are not trivially small (the comparison means something).
                with h5py.File(path, "r") as f:
                    self.assertGreater(float(np.abs(f["probe/v_cfg"][()]).max()), 0.1)
                    self.assertGreater(float(np.abs(f["probe/v_cond"][()] - f["probe/v_uncond"][()]).max()), 1e-3)
        if "flow_standard" in self.files:
            self.assertEqual(FlowReference(self.files["flow_standard"][1]).arch["text_adapter"], 1)

    def test_check_command(self):
        r = reference("check", self.files["flow_tiny"][1])
        self.assertEqual(r.returncode, 0, r.stdout + r.stderr)
        self.assertIn("OK: largest difference", r.stdout)

    def test_a_changed_weight_is_detected(self):
        path = self.copy()
        with h5py.File(path, "a") as f:
            w = f["weights/transformer.blocks.1.mlp.w2.weight"]
            w[...] = w[()] + np.float32(0.01)
        motionio.seal_h5_file(path)
        diffs = FlowReference(path).check_probe()
        self.assertGreater(diffs["v_cfg"], 10 * TOLERANCE)
        r = reference("check", path)
        self.assertEqual(r.returncode, 1, r.stdout + r.stderr)
        self.assertIn("MISMATCH", r.stdout)

    def test_sample(self):
        out = os.path.join(self.tmp, "sample.npy")
        r = reference("sample", self.files["flow_tiny"][1], "--caption", "a person walks forward", "--length", 12,
                      "--steps", 3, "--out", out)
        self.assertEqual(r.returncode, 0, r.stdout + r.stderr)
        world = np.load(out)
        self.assertEqual(world.shape, (12, 22, 3))
        self.assertTrue(np.isfinite(world).all())

    # ---------------------------------------------------------------- layout

    def test_layout(self):
        for name, (run_dir, path) in self.files.items():
            with self.subTest(prior=name), h5py.File(path, "r") as f:
                self.assertEqual(f.attrs["format"], "motionctl.flow_weights")
                self.assertEqual(int(f.attrs["format_version"]), 2)
                self.assertEqual(int(f["model"].attrs["kinematic_head"]), int(name == "flow_standard_kin"))
                # The config hash is the suffix of the run's default name.
                self.assertEqual(f.attrs["config_hash"], run_dir.rsplit("-", 1)[1])
                with open(os.path.join(run_dir, "config.yaml"), encoding="utf-8") as c:
                    self.assertEqual(f.attrs["config"], c.read())
                self.assertIn("type: flow_prior", f.attrs["model_config"])
                with open(os.path.join(run_dir, "outputs", "vocab.txt"), encoding="utf-8") as v:
                    self.assertEqual([w.decode() for w in f["vocab"][()]], v.read().split("\n")[:-1])
                self.assertEqual(len(f["skeleton/names"]), int(f.attrs["num_joints"]))
                self.assertEqual(f["skeleton/parents"][0], -1)
                names = set(f["weights"].keys())
                for k in names:
                    self.assertEqual(f["weights"][k].dtype, np.float32, k)
                self.assertIn("joint_mean", names)
                self.assertIn("joint_std", names)
            # Every tensor in the file is one the loader checks and uses, and none is missing.
            self.assertEqual(names, set(FlowReference(path).p), name)

    def test_export_is_deterministic(self):
        run_dir, path = self.files["flow_tiny"]
        again = os.path.join(self.tmp, "again.h5")
        r = run("export", "--format", "weights", run_dir, "--out", again, "--probe")
        self.assertEqual(r.returncode, 0, r.stdout + r.stderr)
        with open(path, "rb") as a, open(again, "rb") as b:
            self.assertEqual(a.read(), b.read())

    # ---------------------------------------------------------------- damaged files

    def test_missing_dataset_is_named(self):
        path = self.copy()
        with h5py.File(path, "a") as f:
            del f["weights/transformer.blocks.0.attn.qkv.weight"]
        motionio.seal_h5_file(path)  # edited on purpose: the loader's own checks must catch it
        with self.assertRaisesRegex(FlowWeightsError, r"'/weights/transformer\.blocks\.0\.attn\.qkv\.weight' is missing"):
            FlowReference(path)
        r = reference("check", path)
        self.assertEqual(r.returncode, 2)
        self.assertIn("transformer.blocks.0.attn.qkv.weight", r.stderr)
        self.assertIn("motionctl export --format weights", r.stderr)

    def test_reshaped_and_non_finite_datasets_are_named(self):
        path = self.copy()
        with h5py.File(path, "a") as f:
            del f["weights/null_text"]
            f["weights/null_text"] = np.zeros(3, np.float32)
        motionio.seal_h5_file(path)
        with self.assertRaisesRegex(FlowWeightsError, r"'/weights/null_text' has shape \(3,\)"):
            FlowReference(path)
        with h5py.File(path, "a") as f:
            del f["weights/null_text"]
            f["weights/null_text"] = np.full(f["weights/text.out.bias"].shape, np.nan, np.float32)
        motionio.seal_h5_file(path)
        with self.assertRaisesRegex(FlowWeightsError, r"'/weights/null_text' holds non-finite values"):
            FlowReference(path)

    def test_inconsistent_kinematic_attributes_are_refused(self):
        """Version 2's head attributes must agree with each other and with the layout."""
        if "flow_standard_kin" not in self.files:
            self.skipTest("pretrained/prior/flow_standard_kin-<hash> is not shipped")
        cases = [
            ({"out_channels": 7}, r"/model out_channels 7 does not match kinematic_head 1 with 22 joints "
                                  r"\(expected 68\)"),
            ({"prediction": "velocity"}, r"kinematic_head 1 with prediction 'velocity'"),
            ({"kinematic_head": 0, "kinematic_noise": 1, "out_channels": 66},
             r"kinematic_noise 1 without kinematic_head"),
        ]
        for attrs, message in cases:
            with self.subTest(attrs=attrs):
                path = self.copy("flow_standard_kin")
                with h5py.File(path, "a") as f:
                    for k, v in attrs.items():
                        f["model"].attrs[k] = v
                motionio.seal_h5_file(path)
                with self.assertRaisesRegex(FlowWeightsError, message):
                    FlowReference(path)
                r = reference("check", path)
                self.assertEqual(r.returncode, 2, r.stdout + r.stderr)
                self.assertIn("motionctl export --format weights", r.stderr)

    def test_missing_probe_dataset_is_named(self):
        path = self.copy()
        with h5py.File(path, "a") as f:
            del f["probe/v_uncond"]
        motionio.seal_h5_file(path)
        with self.assertRaisesRegex(FlowWeightsError, r"'/probe/v_uncond' is missing"):
            FlowReference(path).check_probe()

    def test_damaged_file_is_refused(self):
        path = self.copy()
        size = os.path.getsize(path)
        with open(path, "r+b") as f:  # a flipped byte in the middle of the weights
            f.seek(size // 2)
            b = f.read(1)
            f.seek(size // 2)
            f.write(bytes([b[0] ^ 0xFF]))
        with self.assertRaisesRegex(FlowWeightsError, "damaged"):
            FlowReference(path)
        with self.assertRaisesRegex(FlowWeightsError, "no such file"):
            FlowReference(os.path.join(self.tmp, "absent.h5"))
        r = reference("check", os.path.join(self.tmp, "absent.h5"))
        self.assertEqual(r.returncode, 2)

    # ---------------------------------------------------------------- refused exports

    def test_export_refuses_bad_runs(self):
        out = os.path.join(self.tmp, "refused.h5")
        missing = os.path.join(self.tmp, "no_such_run")
        r = run("export", "--format", "weights", missing, "--out", out)
        self.assertEqual(r.returncode, 2, r.stdout + r.stderr)
        self.assertIn(f"'{missing}' does not exist", r.stderr)
        self.assertIn("motionctl train configs/prior/flow_tiny.yaml", r.stderr)

        tmd = os.path.join(REPO, "pretrained", "tmd")
        tmd_runs = sorted(os.listdir(tmd)) if os.path.isdir(tmd) else []
        if tmd_runs:
            r = run("export", "--format", "weights", os.path.join(tmd, tmd_runs[0]), "--out", out)
            self.assertEqual(r.returncode, 2, r.stdout + r.stderr)
            self.assertIn("model type 'tmd_prior'", r.stderr)
            self.assertIn("only flow priors", r.stderr)

        unfinished = os.path.join(self.tmp, "unfinished")
        shutil.copytree(self.files["flow_tiny"][0], unfinished)
        os.remove(os.path.join(unfinished, "DONE"))
        r = run("export", "--format", "weights", unfinished, "--out", out)
        self.assertEqual(r.returncode, 2, r.stdout + r.stderr)
        self.assertIn("is not finished", r.stderr)
        self.assertIn(f"motionctl train {unfinished}/config.yaml", r.stderr)

        r = run("export", "--format", "weights", self.files["flow_tiny"][0], "--out", out, "--ids", "a")
        self.assertEqual(r.returncode, 2, r.stdout + r.stderr)
        self.assertIn("--ids does not apply to --format weights", r.stderr)
        self.assertFalse(os.path.exists(out))


if __name__ == "__main__":
    unittest.main(verbosity=2)
