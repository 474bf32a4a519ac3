"""Tests for tools/figures.py: a synthetic results.h5 in the replay's layout yields every figure; a
tables-only file yields fewer (exit 0); bad input exits 2 naming the file; the statistics and the
camera used by the figures are checked against hand-computed numbers."""

import json
import math
import os
import re
import shutil
import subprocess
import sys
import tempfile
import unittest

from tools_test_util import REPO, TOOLS, require_modules

require_modules("numpy", "h5py", "matplotlib")
import numpy as np  # noqa: E402
import h5py  # noqa: E402
import matplotlib  # noqa: E402
matplotlib.use("Agg")
import matplotlib.image as plt_image  # noqa: E402
import motionio  # noqa: E402
import figures  # noqa: E402

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
SKELETON = motionio.load_skeleton_yaml(os.path.join(REPO, "configs", "skeletons", "humanml3d22.yaml"))
STR = h5py.string_dtype(encoding="utf-8")


def run_figures(*args):
    return subprocess.run([sys.executable, os.path.join(TOOLS, "figures.py"), *map(str, args)],
                          capture_output=True, text=True, timeout=300)


def rot_x(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def walk(frames, path_fn, phase=0.0):
    """A crude walk: legs and arms swing about the lateral axis while the body follows path_fn(t) -> (x, z)
    facing along the path; feet roughly on the floor. [frames, 22, 3] float32."""
    parents, dirs, lengths = SKELETON["parents"], SKELETON["rest_directions"], SKELETON["bone_lengths"]
    offsets = dirs * lengths[:, None]
    swing = {1: 0.45, 2: -0.45, 16: -0.35, 17: 0.35}  # l_hip, r_hip, l_shoulder, r_shoulder
    out = np.zeros((frames, len(parents), 3))
    for t in range(frames):
        s = math.sin(2 * math.pi * t / 20.0 + phase)
        local = {j: rot_x(a * s) for j, a in swing.items()}
        local[4] = rot_x(0.5 * max(0.0, -s))    # knees bend on the back swing
        local[5] = rot_x(0.5 * max(0.0, s))
        glob = [np.eye(3)] * len(parents)
        pos = np.zeros((len(parents), 3))
        for j in range(1, len(parents)):
            p = parents[j]
            glob[j] = glob[p] @ local.get(j, np.eye(3))  # a joint's rotation moves its descendants
            pos[j] = pos[p] + glob[p] @ offsets[j]
        x0, z0 = path_fn(t)
        x1, z1 = path_fn(t + 1)
        heading = math.atan2(x1 - x0, z1 - z0)  # +Z forward at heading 0
        pos = pos @ rot_y(heading).T
        pos[:, 1] -= pos[:, 1].min()
        pos[:, 0] += x0
        pos[:, 2] += z0
        out[t] = pos
    return out.astype(np.float32)


def s_path(t):
    return 0.6 * math.sin(t / 12.0), 0.07 * t


def write_tables(f, rng):
    def table(tid, title, columns, rows, paper=()):
        g = f.create_group("tables/" + tid.replace("/", "|"))
        g.attrs["title"] = title
        g.attrs["columns"] = ",".join(columns)
        for i, (rid, label, values) in enumerate(rows):
            r = g.create_group(rid.replace("/", "|"))
            r.attrs.update({"label": label, "run_dir": f"runs/{rid}", "generator": "synthetic", "order": str(i)})
            for m, v in values.items():
                r.create_dataset(m.replace("/", "|"), data=np.asarray(v, np.float64))
        for i, (method, section, kind, ours_id, values) in enumerate(paper):
            p = g.create_group(f"_paper/{i:03d}")
            p.attrs.update({"method": method, "section": section, "kind": kind, "ours_id": ours_id})
            for m, v in values.items():
                p.create_dataset(m, data=float(v))

    def reps(mean, spread):
        return mean + spread * rng.standard_normal(3)

    frontier = []
    for fam, fid0, err0 in (("root3d", 0.3, 0.11), ("planar", 0.35, 0.13), ("body", 0.32, 0.10)):
        for steps in (0, 100, 200, 500):
            k = steps / 500
            frontier.append((f"{fam}/rs{steps}", f"AnchorRoute RS{steps} ({fam})",
                             {"fid": reps(fid0 + 0.4 * k, 0.02), "control_error": reps(err0 * (1 - 0.8 * k), 0.005),
                              f"control_error@family={fam}": reps(err0 * (1 - 0.8 * k), 0.005),
                              "r_precision_top3": reps(0.7, 0.01)}))
    frontier.append(("anchorkv", "Generator only", {"fid": reps(0.3, 0.02)}))
    table("anchorroute/table5", "Refinement ablations at RS200", ["fid", "control_error", "r_precision_top3"],
          frontier,
          paper=[("Generator only", "root_3d", "ours", "anchorkv", {"fid": 0.066, "control_error": 0.110}),
                 ("RouteSolver", "root_3d", "ours", "anchorroute/rs200", {"fid": 0.185, "control_error": 0.040}),
                 ("Plain", "root_3d", "ablation", "routesolver/plain", {"fid": 0.231, "control_error": 0.030}),
                 ("RouteSolver", "planar_root", "ours", "anchorroute/rs200", {"fid": 0.120, "control_error": 0.02})])
    table("cross/table5", "Cross-dataset frontier", ["fid", "control_error"],
          [("root3d/rs0", "RS0", {"fid": reps(0.5, 0.03), "control_error": reps(0.12, 0.01)}),
           ("root3d/rs200", "RS200", {"fid": reps(0.7, 0.03), "control_error": reps(0.05, 0.01)})])
    ctrl = {"fid": reps(0.4, 0.05), "r_precision_top3": reps(0.7, 0.01), "traj_err": reps(0.01, 0.002),
            "loc_err": reps(0.005, 0.001), "avg_err": reps(0.02, 0.002), "foot_skating": reps(0.06, 0.003)}
    table("projflow/table1", "Spatial control", list(ctrl),
          [("pelvis/projflow", "ACMDM-S-PS22+ProjFlow", ctrl),
           ("pelvis/dno", "ACMDM-S-PS22+DNO ($\\lambda$ = 1)", ctrl),  # '$' must stay literal
           ("pelvis/guidance", "Guidance (diverged)", ctrl),
           ("all/projflow", "ProjFlow (all joints)", ctrl)])
    table("projflow/table2", "2D-to-3D lifting", ["fid", "mpjpe_2d"],
          [("average/projflow", "ProjFlow (average)", {"fid": reps(0.5, 0.05), "mpjpe_2d": reps(0.0, 0.0)})])


def write_examples(f, rng):
    K, T, J = 2, 30, 22
    lengths = np.array([30, 24], np.int32)

    def example(tid, rid, make, controlled_joints, camera=False):
        g = f.create_group(f"examples/{tid.replace('/', '|')}/{rid.replace('/', '|')}")
        joints = np.zeros((K, T, J, 3), np.float32)
        target = np.zeros((K, T, J, 3), np.float32)
        controlled = np.zeros((K, T, J, 3), np.uint8)
        for k in range(K):
            n = lengths[k]
            target[k, :n] = walk(n, s_path, phase=0.3 * k)
            joints[k, :n] = make(target[k, :n])
            controlled[k, :n:5, controlled_joints, :] = 1
        g.create_dataset("joints", data=joints)
        g.create_dataset("lengths", data=lengths)
        g.create_dataset("target", data=target)
        g.create_dataset("controlled", data=controlled)
        if camera:
            g.create_dataset("camera", data=np.array([[1.1, 15.0, 30.0, 0.0], [0.9, 5.0, -20.0, 0.0]]))
            c2 = np.zeros((K, T, J), np.uint8)
            c2[:, 0, :] = 1          # initial 2D key pose
            c2[:, :, 20] = 1         # left-wrist 2D trajectory
            for k in range(K):
                c2[k, lengths[k]:] = 0
            g.create_dataset("controlled_2d", data=c2)
        g.attrs["captions"] = "a person walks along an S-shaped path\na person walks and waves for $5"
        g.attrs["task_ids"] = "task_000\ntask_001"

    def drift(clip):  # a generated motion that misses the target a little
        return clip + np.array([0.05, 0.0, -0.04]) * np.linspace(0, 1, len(clip))[:, None, None]

    def diverged(clip):  # a baseline that blew up: joints tens of metres apart, growing over time
        grow = np.linspace(0.0, 1.0, len(clip))[:, None, None]
        return clip + grow * np.array([3.0, 25.0, -30.0]) * (np.arange(22)[None, :, None] % 3)

    example("projflow/table1", "pelvis/projflow", lambda c: c, [0])
    example("projflow/table1", "pelvis/dno", drift, [0])
    example("projflow/table1", "pelvis/guidance", diverged, [0])
    example("projflow/table1", "all/projflow", lambda c: c, [0, 10, 20])
    example("projflow/table2", "average/projflow", drift, [], camera=True)
    example("anchorroute/table5", "root3d/rs200", lambda c: c + 0.02 * rng.standard_normal(c.shape), [0])
    for i in range(MANY_ROWS):  # more rows than one column of strips holds: they wrap into columns
        example("anchorroute/table6", f"body/v{i:02d}", lambda c: c, [20])


def write_rest(f):
    s = f.create_group("skeleton")
    s.create_dataset("parents", data=np.asarray(SKELETON["parents"], np.int32))
    s.attrs["joint_names"] = "\n".join(SKELETON["names"])
    steps = np.arange(50, 2001, 50, dtype=np.float64)
    for comp, parts in (("flow_prior", {"fm": 1.0}), ("tokenizer", {"rec": 0.7, "vel": 0.3}),
                        ("evaluator", {"contrastive": 1.0})):
        g = f.create_group(f"training/{comp}")
        g.attrs["run_dir"] = f"runs/{comp}-0123456789ab"
        total = np.zeros_like(steps)
        for name, w in parts.items():
            v = w * (0.05 + 2.0 * np.exp(-steps / 400.0))
            g.create_dataset(name, data=v)
            total += v
        g.create_dataset("step", data=steps)
        g.create_dataset("wall_time", data=1.7e9 + steps)
        g.create_dataset("lr", data=np.full_like(steps, 2e-4))
        g.create_dataset("loss", data=total)
        g.create_dataset("grad_norm", data=np.ones_like(steps))


def build_results(path, examples=True, training=True):
    rng = np.random.default_rng(7)
    with h5py.File(path, "w") as f:
        f.attrs["profile"] = "smoke"
        f.attrs["commit"] = "abc1234"
        write_tables(f, rng)
        if examples:
            write_examples(f, rng)
        if training:
            write_rest(f)


MANY_ROWS = 11
ALL_PNGS = sorted(["frontier_body.png", "frontier_planar.png", "frontier_root3d.png", "lifting_example.png",
            "strips_anchorroute_table5.png", "strips_anchorroute_table6.png", "strips_projflow_table1.png",
            "strips_projflow_table2.png", "trajectory_overlay.png", "training_curves.png"])


class Figures(unittest.TestCase):
    @classmethod
    def setUpClass(cls):
        cls.tmp = tempfile.mkdtemp(prefix="figures_")
        cls.full = os.path.join(cls.tmp, "results.h5")
        build_results(cls.full)

    @classmethod
    def tearDownClass(cls):
        if not os.environ.get("KEEP_FIGURES"):
            shutil.rmtree(cls.tmp, ignore_errors=True)

    def assert_png(self, path):
        self.assertTrue(os.path.isfile(path), path)
        with open(path, "rb") as f:
            self.assertEqual(f.read(8), PNG_MAGIC, path)
        self.assertGreater(os.path.getsize(path), 5000, path)

    def test_full_file_draws_every_figure(self):
        out = os.path.join(self.tmp, "full")
        manifest = os.path.join(self.tmp, "manifest.json")
        r = run_figures(self.full, "--out", out, "--manifest", manifest)
        self.assertEqual(r.returncode, 0, r.stderr)
        self.assertEqual(sorted(os.listdir(out)), ALL_PNGS)
        self.assertEqual(sorted(r.stdout.split()), [os.path.join(out, n) for n in ALL_PNGS])
        for name in ALL_PNGS:
            self.assert_png(os.path.join(out, name))
        self.assertNotIn("skipped", r.stderr)
        with open(manifest) as f:
            panels = json.load(f)
        self.assertEqual(sorted(panels), ALL_PNGS)
        for name in ALL_PNGS:
            self.assert_openable_and_full(os.path.join(out, name), panels[name])
        # The diverged guidance row: its own zoom per panel in the strips, its own scale in the overlay;
        # every other row keeps one scale.
        strips = panels["strips_projflow_table1.png"]["panels"]
        zoomed = [p["title"] for p in strips if re.search(r", [0-9.]+ m$", p["title"])]
        self.assertTrue(zoomed, "diverged row has no per-panel zoom")
        self.assertLess(len(zoomed), len(strips) // 2)
        overlay = [p["title"] for p in panels["trajectory_overlay.png"]["panels"]]
        self.assertEqual(sum("diverged" in t for t in overlay), 1, overlay)
        # Eleven rows wrap into two columns of strips instead of one tall figure.
        w, h = panels["strips_anchorroute_table6.png"]["size"]
        self.assertGreater(w, 1.5 * panels["strips_anchorroute_table5.png"]["size"][0])
        self.assertLess(h, 8 * 300)
        if os.environ.get("KEEP_FIGURES"):
            print("figures kept in", out)

    def assert_openable_and_full(self, path, entry):
        """Bounded, the size the manifest says, and every panel shows something: its subject (pose,
        path or curve) lies in view, spans a tenth of the panel, and left ink in the PNG there."""
        img = plt_image.imread(path)
        h, w = img.shape[:2]
        self.assertEqual([w, h], entry["size"], path)
        self.assertLessEqual(max(w, h), 4000, path)
        self.assertTrue(entry["panels"], path)
        for p in entry["panels"]:
            where = f"{os.path.basename(path)} panel '{p['title']}' at {[round(v) for v in p['box']]}"
            self.assertIsNotNone(p["subject"], f"{where}: nothing drawn in view")
            bx0, by0, bx1, by1 = p["box"]
            sx0, sy0, sx1, sy1 = p["subject"]
            self.assertGreater(max((sx1 - sx0) / (bx1 - bx0), (sy1 - sy0) / (by1 - by0)), 0.1,
                               f"{where}: what it shows is a speck ({sx1 - sx0:.0f} x {sy1 - sy0:.0f} px)")
            region = img[int(sy0):int(math.ceil(sy1)) + 1, int(sx0):int(math.ceil(sx1)) + 1, :3]
            ink = (np.abs(region - 1.0).max(axis=-1) > 0.2).sum()
            self.assertGreater(ink, 10, f"{where}: no ink where its subject is")

    def test_tables_only_file(self):
        path = os.path.join(self.tmp, "tables_only.h5")
        build_results(path, examples=False, training=False)
        out = os.path.join(self.tmp, "tables_only")
        r = run_figures(path, "--out", out)
        self.assertEqual(r.returncode, 0, r.stderr)
        expected = ["frontier_body.png", "frontier_planar.png", "frontier_root3d.png"]
        self.assertEqual(sorted(os.listdir(out)), expected)
        for name in expected:
            self.assert_png(os.path.join(out, name))
        for what in ("trajectory_overlay", "lifting_example", "training_curves", "strips_"):
            self.assertIn(f"skipped: {what}", r.stderr)

    def test_no_frontier_tables(self):
        path = os.path.join(self.tmp, "no_frontier.h5")
        build_results(path)
        with h5py.File(path, "a") as f:
            del f["tables/anchorroute|table5"]
            del f["tables/cross|table5"]
        out = os.path.join(self.tmp, "no_frontier")
        r = run_figures(path, "--out", out)
        self.assertEqual(r.returncode, 0, r.stderr)
        self.assertFalse(any(n.startswith("frontier_") for n in os.listdir(out)))
        self.assertIn("trajectory_overlay.png", os.listdir(out))
        self.assertIn("skipped: frontier_", r.stderr)


class Helpers(unittest.TestCase):
    def test_metric_stats_is_mean_and_95pct_ci_with_population_std(self):
        mean, ci, n = figures.metric_stats([1.0, 2.0, 4.0, float("nan")])
        self.assertEqual(n, 3)
        self.assertAlmostEqual(mean, 7.0 / 3.0)
        pop_std = math.sqrt(((1 - 7 / 3) ** 2 + (2 - 7 / 3) ** 2 + (4 - 7 / 3) ** 2) / 3)
        self.assertAlmostEqual(ci, 1.96 * pop_std / math.sqrt(3))
        self.assertEqual(figures.metric_stats([5.0])[1], 0.0)
        self.assertIsNone(figures.metric_stats([float("inf")]))

    def test_camera_matches_the_reference_convention(self):
        p = np.array([0.3, 1.2, -0.7])
        np.testing.assert_allclose(figures.project(p, [2.0, 0, 0, 0]), [0.6, 2.4])
        # yaw 90: R_y maps x <- z, so u = z.
        np.testing.assert_allclose(figures.project(p, [1.0, 0, 90, 0]), [-0.7, 1.2], atol=1e-12)
        # pitch 90: R_x maps y <- -z.
        np.testing.assert_allclose(figures.project(p, [1.0, 90, 0, 0]), [0.3, 0.7], atol=1e-12)
        # roll 90: R_z maps (x, y) <- (-y, x).
        np.testing.assert_allclose(figures.project(p, [1.0, 0, 0, 90]), [-1.2, 0.3], atol=1e-12)
        # Order: roll after pitch after yaw.
        cam = [1.3, 20.0, -35.0, 10.0]
        a, b, c = (math.radians(v) for v in cam[1:])
        rz = np.array([[math.cos(c), -math.sin(c), 0], [math.sin(c), math.cos(c), 0], [0, 0, 1]])
        expected = 1.3 * (rz @ rot_x(a) @ rot_y(b) @ p)[:2]
        np.testing.assert_allclose(figures.project(p, cam), expected, atol=1e-12)

    def test_frontier_points_in_step_order_and_paper_mapping(self):
        tables = [figures.Table("anchorroute/table5", "", [
            figures.Row("body/rs500", "", 0, {"fid": np.array([3.0, 5.0]), "control_error": np.array([0.1, 0.1])}),
            figures.Row("body/rs0", "", 1, {"fid": np.array([1.0]), "control_error@family=body": np.array([0.4])}),
            figures.Row("body/rs100", "", 2, {"fid": np.array([2.0])}),  # no control error: left out
            figures.Row("anchorkv", "", 3, {"fid": np.array([9.0]), "control_error": np.array([9.0])})],
            [{"method": "g", "section": "body_point", "kind": "ours", "ours_id": "anchorkv",
              "values": {"fid": 0.066, "control_error": 0.11}},
             {"method": "r", "section": "body_point", "kind": "ours", "ours_id": "anchorroute/rs200",
              "values": {"fid": 0.099, "control_error": 0.024}},
             {"method": "r", "section": "root_3d", "kind": "ours", "ours_id": "anchorroute/rs200",
              "values": {"fid": 0.185, "control_error": 0.04}}]),
            figures.Table("projflow/table1", "", [
                figures.Row("body/rs200", "", 0, {"fid": np.array([1.0]), "control_error": np.array([1.0])})], [])]
        notes = []
        pts = figures.frontier_points(tables, notes)
        self.assertEqual(list(pts), ["body"])
        got = pts["body"]["anchorroute/table5"]
        self.assertEqual([p[0] for p in got], [0, 500])
        self.assertAlmostEqual(got[0][1][0], 0.4)
        self.assertAlmostEqual(got[1][2][0], 4.0)
        self.assertAlmostEqual(got[1][2][1], 1.96 * 1.0 / math.sqrt(2))
        self.assertEqual(len(notes), 1)
        self.assertIn("body/rs100", notes[0])
        self.assertEqual(figures.paper_frontier(tables, "body"), [(0, 0.11, 0.066), (200, 0.024, 0.099)])
        self.assertEqual(figures.paper_frontier(tables, "root3d"), [(200, 0.04, 0.185)])
        self.assertEqual(figures.paper_frontier(tables, "planar"), [])


class Layout(unittest.TestCase):
    def example(self, target_paths, controlled):
        """An Example whose sample k's ground-truth root follows target_paths[k] ([T, 2] xz)."""
        k, t = len(target_paths), len(target_paths[0])
        target = np.zeros((k, t, 22, 3))
        for i, path in enumerate(target_paths):
            target[i, :, :, 0] = path[:, None, 0]
            target[i, :, :, 2] = path[:, None, 1]
            target[i, :, :, 1] = np.linspace(0, 1.7, 22)[None, :]
        ctrl = np.zeros((k, t, 22, 3), bool)
        for i in controlled:
            ctrl[i, 3, 0] = True
        return figures.Example("r", "r", target.copy(), np.full(k, t), target, ctrl, None, None, [], [])

    def test_informative_sample_prefers_controlled_then_moving(self):
        still = np.zeros((20, 2))
        walk = np.stack([np.zeros(20), np.linspace(0, 3, 20)], axis=1)
        self.assertEqual(figures.informative_sample([self.example([still, walk, still], [0, 1, 2])]), 1)
        self.assertEqual(figures.informative_sample([self.example([still, walk], [0])]), 0)
        self.assertEqual(figures.informative_sample([self.example([still, still], [])]), 0)

    def test_diverged_split(self):
        self.assertEqual(figures.split_diverged([1.9, 2.0, 2.1, 40.0]), {3})
        self.assertEqual(figures.split_diverged([1.9, 2.0, 5.5]), set())

    def test_strip_pages_stay_within_4000_px(self):
        for n in (1, 5, 8, 9, 30, 60, 200):
            pages = figures.strip_pages(n, 9.4, 2.9, 0.75, 0.25)
            self.assertEqual(sum(p[1] for p in pages), n)
            for first, count, cols, per_col in pages:
                self.assertLessEqual((cols * 9.4 + 0.1) * figures.DPI, 4000)
                self.assertLessEqual((0.75 + per_col * 2.9 + 0.25) * figures.DPI, 4000)
                self.assertLessEqual(count, cols * per_col)
        self.assertEqual(figures.strip_pages(8, 9.4, 2.9, 0.75, 0.25), [(0, 8, 1, 8)])
        self.assertEqual(len(figures.strip_pages(200, 9.4, 2.9, 0.75, 0.25)), 4)


class BadInput(unittest.TestCase):
    def setUp(self):
        self.tmp = tempfile.mkdtemp(prefix="figures_bad_")
        self.out = os.path.join(self.tmp, "out")

    def tearDown(self):
        shutil.rmtree(self.tmp, ignore_errors=True)

    def assert_rejected(self, path, *needles):
        r = run_figures(path, "--out", self.out)
        self.assertEqual(r.returncode, 2, r.stdout + r.stderr)
        self.assertIn(path, r.stderr)
        for n in needles:
            self.assertIn(n, r.stderr)
        self.assertNotIn("Traceback", r.stderr)
        self.assertFalse(os.path.exists(self.out), "output created for bad input")

    def test_missing_file(self):
        self.assert_rejected(os.path.join(self.tmp, "nope.h5"), "no such file")

    def test_not_hdf5(self):
        path = os.path.join(self.tmp, "text.h5")
        with open(path, "w") as f:
            f.write("fid,0.1\n")
        self.assert_rejected(path, "not an HDF5 file")

    def test_no_tables_group(self):
        path = os.path.join(self.tmp, "motion.h5")
        with h5py.File(path, "w") as f:
            f.create_dataset("joints", data=np.zeros((1, 2, 22, 3), np.float32))
        self.assert_rejected(path, "/tables")

    def test_malformed_example(self):
        path = os.path.join(self.tmp, "bad_example.h5")
        build_results(path)
        with h5py.File(path, "a") as f:
            del f["examples/projflow|table1/pelvis|dno/target"]
            f["examples/projflow|table1/pelvis|dno/target"] = np.zeros((2, 30, 21, 3), np.float32)
        self.assert_rejected(path, "pelvis|dno/target")


if __name__ == "__main__":
    unittest.main()
