"""A real client opens our BVH (issue 17): `motionctl export --format bvh` files are imported by
Blender's own BVH importer, headless, and the joint positions Blender reports for every frame match
the motion file's (rigid motion in the standard layout; fixture clips and non-rigid motion, as
generated samples are, in the every-joint-translated layout). Skipped (exit 77) when Blender or the binary is absent."""

import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import unittest

from tools_test_util import BINARY, REPO, require_modules, skip

require_modules("numpy", "h5py")
import numpy as np  # noqa: E402
import motionio  # noqa: E402

BLENDER = shutil.which("blender")
if BLENDER is None or not os.access(BINARY, os.X_OK):
    skip("needs Debian's blender and the motionctl binary (set MOTIONCTL_BINARY)")

# Run inside Blender: import each BVH with the stock importer (Y up, -Z forward: Blender's
# defaults for BVH) and report the world position of every bone head at every frame.
BLENDER_SCRIPT = r"""
import bpy, builtins, json, sys
import io_anim_bvh.import_bvh as importer
# Debian's Blender 3.4.1 runs on Python 3.11, which removed open()'s "U" mode that this
# importer still passes ('rU': ValueError: invalid mode). Blender 3.5 dropped it upstream; shim it
# for the importer's module only.
importer.open = lambda file, mode="r", *a, **k: builtins.open(file, mode.replace("U", ""), *a, **k)
paths, out = sys.argv[sys.argv.index("--") + 1:-1], sys.argv[-1]
result = {}
for path in paths:
    bpy.ops.object.select_all(action="DESELECT")
    bpy.ops.import_anim.bvh(filepath=path, global_scale=1.0, frame_start=1, use_fps_scale=False,
                            rotate_mode="NATIVE", axis_forward="-Z", axis_up="Y")
    arm = bpy.context.selected_objects[0]
    frames = int(arm.animation_data.action.frame_range[1])
    scene = bpy.context.scene
    per_frame = []
    for f in range(1, frames + 1):
        scene.frame_set(f)
        per_frame.append({pb.name: list(arm.matrix_world @ pb.head) for pb in arm.pose.bones})
    result[path] = per_frame
with open(out, "w") as fh:
    json.dump(result, fh)
"""


def rotation_zxy(z, x, y):
    cz, sz, cx, sx, cy, sy = np.cos(z), np.sin(z), np.cos(x), np.sin(x), np.cos(y), np.sin(y)
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    return rz @ rx @ ry


def rigid_clip(skeleton, frames, rng):
    """Joints from BVH-convention forward kinematics (a joint's rotation turns its children's offsets)
    with smooth random local rotations: motion a rigid BVH holds exactly."""
    parents, offsets = skeleton["parents"], skeleton["rest_directions"] * skeleton["bone_lengths"][:, None]
    phase = rng.uniform(0, 2 * np.pi, (len(parents), 3))
    out = np.zeros((frames, len(parents), 3))
    for t in range(frames):
        g = [None] * len(parents)
        for j, p in enumerate(parents):
            local = rotation_zxy(*(0.5 * np.sin(0.2 * t + phase[j])))
            if p < 0:
                g[j], out[t, j] = local, [0.05 * t, 0.9, 0.02 * t]
            else:
                out[t, j] = out[t, p] + g[p] @ offsets[j]
                g[j] = g[p] @ local
    return out.astype(np.float32)


def run(*args, timeout=600):
    return subprocess.run(list(map(str, args)), cwd=REPO, capture_output=True, text=True, timeout=timeout,
                          env=dict(os.environ, OMP_NUM_THREADS="1", CI="1"))


class BlenderImport(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="bvh_blender_")
        fx = os.path.join(cls.tmp, "fx.h5")
        r = run(BINARY, "fixture", "configs/data/smoke.yaml", f"output={fx}", "fixture.num_clips=12")
        assert r.returncode == 0, r.stdout + r.stderr
        fixture = motionio.read_motion(fx)
        # Non-rigid motion like a generated sample's: bones stretch and shrink by a few centimetres;
        # and rigid motion (BVH-style forward kinematics on the skeleton), which gets the standard layout.
        rng = np.random.default_rng(3)
        clips = [fixture.clip(i)[:40] for i in range(2)]
        noisy = [c + rng.normal(0.0, 0.02, c.shape).astype(np.float32) for c in clips]
        gen = os.path.join(cls.tmp, "gen.h5")
        motionio.write_motion(gen, np.stack(noisy + [rigid_clip(fixture.skeleton, 40, rng)]), [40, 40, 40],
                              ["g0", "g1", "rigid"], ["sample"] * 3, [["noisy"], ["noisy"], ["rigid"]])
        cls.expected, cls.bvh, cls.layout = {}, [], {}
        for src, ids, m in ((fx, f"{fixture.ids[0]},{fixture.ids[5]}", fixture),
                            (gen, "g0,rigid", motionio.read_motion(gen))):
            out = os.path.join(cls.tmp, "bvh_" + os.path.basename(src))
            r = run(BINARY, "export", "--format", "bvh", src, "--ids", ids, "--out", out)
            assert r.returncode == 0, r.stdout + r.stderr
            for line in r.stdout.splitlines():
                path = re.match(r"wrote (\S+\.bvh):", line).group(1)
                cid = next(c for c in ids.split(",") if path.endswith(f"_{c}.bvh"))
                cls.expected[path] = (m.clip(m.ids.index(cid)), m.skeleton["names"])
                cls.layout[path] = "every joint translated" in line
                cls.bvh.append(path)
        out = os.path.join(cls.tmp, "blender.json")
        cls.blender = run(BLENDER, "-b", "--factory-startup", "--python-expr", BLENDER_SCRIPT, "--", *cls.bvh, out,
                          timeout=900)
        cls.result = None
        if os.path.exists(out):
            with open(out) as fh:
                cls.result = json.load(fh)

    @classmethod
    def tearDownClass(cls):
        shutil.rmtree(cls.tmp, ignore_errors=True)

    def test_blender_positions_match_ours(self):
        self.assertIsNotNone(self.result, self.blender.stdout[-3000:] + self.blender.stderr[-3000:])
        # Only the rigid clip keeps the standard layout; fixture and noisy clips translate every joint.
        self.assertEqual({os.path.basename(p)[5:]: v for p, v in self.layout.items()},
                         {"fx000000.bvh": True, "fx000005.bvh": True, "g0.bvh": True, "rigid.bvh": False})
        for path in self.bvh:
            clip, names = self.expected[path]
            frames = self.result[path]
            self.assertEqual(len(frames), len(clip), path)
            worst = 0.0
            for t, bones in enumerate(frames):
                for j, name in enumerate(names):
                    # Blender is Z up: ours (x, y, z) is its (x, -z, y).
                    x, y, z = clip[t, j]
                    worst = max(worst, float(np.linalg.norm(np.array(bones[name]) - [x, -z, y])))
            print(f"\n{os.path.basename(path)}: Blender vs motion file, largest joint distance {worst:.2e} m",
                  file=sys.stderr)
            self.assertLess(worst, 1e-4, path)


if __name__ == "__main__":
    unittest.main()
