#!/usr/bin/python3
"""Draw every figure of the paper-table replay from one results.h5 and nothing else: RouteSolver
frontiers, the ProjFlow trajectory overlay and lifting example, training curves, stick-figure strips."""

import argparse
import dataclasses
import json
import math
import os
import re
import sys
import textwrap
from typing import Dict, List, Optional

import numpy as np
import h5py
import matplotlib

matplotlib.use("Agg")
matplotlib.rcParams["text.parse_math"] = False  # captions, labels and ids may contain "$"
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.collections  # noqa: E402
import matplotlib.lines  # noqa: E402
from matplotlib import ticker  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import motionio  # noqa: E402
import render_motion  # noqa: E402

GEN_COLOR, TARGET_COLOR = "#ff7f0e", "0.55"   # ProjFlow Fig. 4: orange generated, grey dotted target
FRONTIER_ROW = re.compile(r"^([^/]+)/rs(\d+)$")
PAPER_FRONTIER_ROW = re.compile(r"^anchorroute/rs(\d+)$")
NOT_LOSS_COLUMNS = {"step", "wall_time", "lr", "grad_norm", "epoch"}
DPI = 100
DEFAULT_FPS = 20.0  # HumanML3D's rate; results.h5 has no fps attribute unless the writer adds one


class ResultsError(Exception):
    """Bad input: reported on stderr with exit code 2."""


def parse_args(argv):
    p = argparse.ArgumentParser(description="Draw the figures of a paper-table replay from its results.h5.")
    p.add_argument("file", help="results.h5 written by the paper-table replay")
    p.add_argument("--out", required=True, help="output folder for the PNGs (created if missing)")
    p.add_argument("--frames", type=int, default=6, help="poses per stick-figure strip (default 6)")
    p.add_argument("--no-paper", action="store_true",
                   help="leave the paper's published points out of the frontier plots")
    p.add_argument("--manifest", default=None,
                   help="also write a JSON file with each figure's size and panel boxes (pixels) and where "
                        "their poses, paths and curves landed (for tests and CI)")
    args = p.parse_args(argv)
    if args.frames < 1:
        p.error("--frames must be >= 1")
    return args


# --------------------------------------------------------------------------
# Reading results.h5 ('/' inside ids is stored as '|' in HDF5 names).

def decode_name(name):
    return name.replace("|", "/")


def attr_str(attrs, key, default=""):
    if key not in attrs:
        return default
    v = attrs[key]
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if isinstance(v, np.ndarray):
        if v.size != 1:
            return default
        v = v.reshape(-1)[0]
        if isinstance(v, bytes):
            return v.decode("utf-8", "replace")
    return str(v)


def safe_name(text):
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "figure"


@dataclasses.dataclass
class Row:
    id: str
    label: str
    order: float
    metrics: Dict[str, np.ndarray]


@dataclasses.dataclass
class Table:
    id: str
    title: str
    rows: List[Row]
    paper: List[dict]     # the paper's rows: method, section, kind, ours_id, values {metric: float}


@dataclasses.dataclass
class Example:
    """The generated samples of one row of /examples/<table>/<row>."""
    row_id: str
    label: str
    joints: np.ndarray                   # [K, T, J, 3]
    lengths: np.ndarray                  # [K]
    target: np.ndarray                   # [K, T, J, 3]
    controlled: np.ndarray               # [K, T, J, 3] bool
    camera: Optional[np.ndarray]         # [K, 4] (scale, pitch_deg, yaw_deg, roll_deg)
    controlled_2d: Optional[np.ndarray]  # [K, T, J] bool
    captions: List[str]
    task_ids: List[str]

    def caption(self, k):
        return self.captions[k] if k < len(self.captions) else ""

    def task_id(self, k):
        return self.task_ids[k] if k < len(self.task_ids) else ""


def open_results(path):
    if not os.path.exists(path):
        raise ResultsError(f"{path}: no such file; pass the results.h5 written by the paper-table replay")
    if not os.path.isfile(path):
        raise ResultsError(f"{path}: not a file; pass the results.h5 written by the paper-table replay")
    try:
        if not h5py.is_hdf5(path):
            raise ResultsError(f"{path}: not an HDF5 file; pass the results.h5 written by the paper-table replay")
        f = h5py.File(path, "r")
    except OSError as e:
        raise ResultsError(f"{path}: cannot open as HDF5 ({e})") from None
    if "tables" not in f or not isinstance(f["tables"], h5py.Group):
        f.close()
        raise ResultsError(f"{path}: no /tables group, so this is not a results.h5 of the paper-table "
                           "replay (expected /tables/<table id>/<row id>/<metric>)")
    return f


def read_vector(f, ds_path, where):
    obj = f[ds_path]
    if not isinstance(obj, h5py.Dataset) or obj.ndim not in (0, 1) or obj.dtype.kind not in "fiu":
        raise ResultsError(f"{where}: /{ds_path} must be a numeric 1-D dataset "
                           f"(one value per replicate)")
    return np.atleast_1d(np.asarray(obj[()], dtype=np.float64))


def read_tables(f, path):
    tables = []
    for tname, tg in f["tables"].items():
        if not isinstance(tg, h5py.Group):
            continue
        rows, paper = [], []
        for position, (rname, rg) in enumerate(tg.items()):
            if not isinstance(rg, h5py.Group):
                continue
            if rname == "_paper":
                for pname, pg in rg.items():
                    if isinstance(pg, h5py.Group):
                        values = {}
                        for m, ds in pg.items():
                            if isinstance(ds, h5py.Dataset) and ds.dtype.kind in "fiu" and ds.size == 1:
                                values[decode_name(m)] = float(np.asarray(ds[()]).reshape(-1)[0])
                        paper.append({k: attr_str(pg.attrs, k) for k in ("method", "section", "kind", "ours_id")}
                                     | {"values": values})
                continue
            metrics = {decode_name(m): read_vector(f, f"tables/{tname}/{rname}/{m}", path)
                       for m, ds in rg.items() if isinstance(ds, h5py.Dataset)}
            order_text = attr_str(rg.attrs, "order")
            try:
                order = float(int(order_text))
            except ValueError:
                order = float(position)
            rid = decode_name(rname)
            rows.append(Row(rid, attr_str(rg.attrs, "label") or rid, order, metrics))
        rows.sort(key=lambda r: (r.order, r.id))
        tables.append(Table(decode_name(tname), attr_str(tg.attrs, "title"), rows, paper))
    return tables


def read_skeleton(f, path):
    """parents and joint names from /skeleton, or None when the file has none."""
    if "skeleton" not in f:
        return None
    g = f["skeleton"]
    if not isinstance(g, h5py.Group) or "parents" not in g:
        raise ResultsError(f"{path}: /skeleton must be a group with a dataset 'parents'")
    parents = np.asarray(g["parents"][()])
    if parents.ndim != 1 or parents.dtype.kind not in "iu":
        raise ResultsError(f"{path}: /skeleton/parents must be a 1-D integer dataset")
    parents = parents.astype(np.int64)
    j = len(parents)
    if any(not (-1 <= parents[c] < c) for c in range(j)):
        raise ResultsError(f"{path}: /skeleton/parents must list each joint's parent before it (-1 = root)")
    names = attr_str(g.attrs, "joint_names").split("\n") if "joint_names" in g.attrs else []
    if len(names) != j:
        names = [f"joint{c}" for c in range(j)]
    return {"parents": parents, "names": names}


def row_labels(tables):
    return {(t.id, r.id): r.label for t in tables for r in t.rows}


def read_examples(f, path, tname, labels):
    """Every row of /examples/<tname> (an HDF5 name) in table row order."""
    out, where = [], f"{path}: /examples/{tname}"
    table_id = decode_name(tname)
    for rname, g in f["examples"][tname].items():
        if not isinstance(g, h5py.Group):
            continue
        loc = f"{where}/{rname}"
        for key in ("joints", "lengths", "target", "controlled"):
            if key not in g or not isinstance(g[key], h5py.Dataset):
                raise ResultsError(f"{loc}: dataset '{key}' is missing")
        joints = np.asarray(g["joints"][()], dtype=np.float64)
        if joints.ndim != 4 or joints.shape[-1] != 3 or min(joints.shape) < 1:
            raise ResultsError(f"{loc}/joints: shape {joints.shape}, expected [K, T, J, 3]")
        k, t, j, _ = joints.shape
        lengths = np.asarray(g["lengths"][()])
        if lengths.shape != (k,) or lengths.dtype.kind not in "iu":
            raise ResultsError(f"{loc}/lengths: expected {k} integers, got shape {lengths.shape}")
        if lengths.min() < 1 or lengths.max() > t:
            raise ResultsError(f"{loc}/lengths: values must lie in 1..{t} (the T of joints)")
        target = np.asarray(g["target"][()], dtype=np.float64)
        controlled = np.asarray(g["controlled"][()]) != 0
        for key, arr, shape in (("target", target, joints.shape), ("controlled", controlled, joints.shape)):
            if arr.shape != shape:
                raise ResultsError(f"{loc}/{key}: shape {arr.shape}, expected {shape} like joints")
        camera = controlled_2d = None
        if "camera" in g:
            camera = np.asarray(g["camera"][()], dtype=np.float64)
            if camera.shape != (k, 4):
                raise ResultsError(f"{loc}/camera: shape {camera.shape}, expected ({k}, 4) = "
                                   "(scale, pitch_deg, yaw_deg, roll_deg) per sample")
        if "controlled_2d" in g:
            controlled_2d = np.asarray(g["controlled_2d"][()]) != 0
            if controlled_2d.shape != (k, t, j):
                raise ResultsError(f"{loc}/controlled_2d: shape {controlled_2d.shape}, expected {(k, t, j)}")
        if not np.isfinite(joints).all() or not np.isfinite(target).all():
            raise ResultsError(f"{loc}: joints or target hold non-finite values")
        rid = decode_name(rname)
        captions = attr_str(g.attrs, "captions").split("\n")
        task_ids = attr_str(g.attrs, "task_ids").split("\n")
        out.append(Example(rid, labels.get((table_id, rid), rid), joints, lengths.astype(np.int64), target,
                           controlled, camera, controlled_2d, captions, task_ids))
    order = {r: i for i, r in enumerate(rid for (t, rid) in labels if t == table_id)}
    out.sort(key=lambda e: (order.get(e.row_id, len(order)), e.row_id))
    return out


# --------------------------------------------------------------------------
# Shared drawing helpers.

def metric_stats(values):
    """(mean, 95% CI half width = 1.96 std / sqrt(n) with the population std, n) of the finite values."""
    v = np.asarray(values, dtype=np.float64)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return None
    return float(v.mean()), 1.96 * float(v.std()) / math.sqrt(v.size), int(v.size)


def footer(fig, info):
    fig.text(0.005, 0.005, info, fontsize=6, color="0.45", ha="left", va="bottom")


# Where each figure's panels are and where what they show landed, in PNG pixels (top-left
# origin), for `--manifest` (the tests check that no panel is empty and every size is bounded).
MANIFEST = {}


def _pixel_box(bbox, fig_h):
    return [float(bbox.x0), float(fig_h - bbox.y1), float(bbox.x1), float(fig_h - bbox.y0)]


def subject_points(artist):
    """Data points of a line, a line collection or a scatter ([N, 2] in the artist's coordinates);
    3D lines give their projection after a draw."""
    if isinstance(artist, matplotlib.lines.Line2D):
        return np.asarray(artist.get_xydata(), dtype=np.float64).reshape(-1, 2)
    if isinstance(artist, matplotlib.collections.LineCollection):
        segs = artist.get_segments()
        return np.concatenate([np.asarray(g, dtype=np.float64).reshape(-1, 2) for g in segs]) if segs else None
    if isinstance(artist, matplotlib.collections.PathCollection):
        return np.asarray(artist.get_offsets(), dtype=np.float64).reshape(-1, 2)
    return None


def panel_manifest(fig):
    """[{box, subject, title}] of every visible panel: the axes' box and the part of its 'subject'
    artists (gid 'subject': poses, paths, curves) that lies inside it (None when nothing does)."""
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    fig_h = fig.get_size_inches()[1] * DPI
    panels = []
    for ax in fig.get_axes():
        if not ax.get_visible():
            continue
        box = ax.get_window_extent(renderer)
        inside = None
        for artist in ax.findobj(lambda a: a.get_gid() == "subject"):
            pts = subject_points(artist)
            if pts is None or not len(pts):
                continue
            pts = artist.get_transform().transform(pts)
            keep = ((pts[:, 0] >= box.x0) & (pts[:, 0] <= box.x1) & (pts[:, 1] >= box.y0) & (pts[:, 1] <= box.y1)
                    & np.isfinite(pts).all(axis=1))
            if not keep.any():
                continue
            lo, hi = pts[keep].min(axis=0), pts[keep].max(axis=0)
            inside = [min(inside[0], lo[0]), min(inside[1], lo[1]), max(inside[2], hi[0]), max(inside[3], hi[1])] \
                if inside else [lo[0], lo[1], hi[0], hi[1]]
        subject = None if inside is None else [inside[0], fig_h - inside[3], inside[2], fig_h - inside[1]]
        panels.append({"box": _pixel_box(box, fig_h), "subject": subject, "title": ax.get_title()})
    return panels


def save(fig, path, written):
    render_motion.check_size(fig, path)
    if MANIFEST.get("enabled"):
        w, h = (fig.get_size_inches() * DPI).round().astype(int).tolist()
        MANIFEST.setdefault("figures", {})[os.path.basename(path)] = {"size": [w, h],
                                                                     "panels": panel_manifest(fig)}
    motionio.atomic_output(path, lambda tmp: fig.savefig(tmp, format="png", dpi=DPI), suffix=".png")
    plt.close(fig)
    written.append(path)


def wrap(text, width):
    return "\n".join(textwrap.wrap(text, width=width)) if text else ""


def camera_matrix(cam):
    """2x3 orthographic projection s * P * R_z(roll) R_x(pitch) R_y(yaw) of cam = (s, pitch, yaw, roll) in degrees."""
    s, pitch, yaw, roll = float(cam[0]), *np.radians(np.asarray(cam[1:4], dtype=np.float64))
    cy, sy, cx, sx, cz, sz = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    r_y = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    r_x = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    r_z = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return s * (r_z @ r_x @ r_y)[:2]


def project(points, cam):
    return points @ camera_matrix(cam).T


# --------------------------------------------------------------------------
# 1. RouteSolver quality-control frontier per anchor family.

def family_matches_section(family, section):
    """Framework families (root3d, planar, body) vs the paper's sections (root_3d, planar_root, body_point)."""
    a, b = re.sub(r"[^a-z0-9]", "", family.lower()), re.sub(r"[^a-z0-9]", "", section.lower())
    return bool(a) and bool(b) and (a.startswith(b) or b.startswith(a))


def frontier_points(tables, notes):
    """{family: {table id: [(steps, (x mean, x ci, n), (y mean, y ci, n))] in step order}}."""
    out = {}
    for t in tables:
        if not (t.id.startswith("anchorroute/table5") or t.id.startswith("cross/")):
            continue
        for r in t.rows:
            m = FRONTIER_ROW.match(r.id)
            if not m:
                continue
            family, steps = m.group(1), int(m.group(2))
            x = next((st for k in ("control_error", f"control_error@family={family}") if k in r.metrics
                      for st in [metric_stats(r.metrics[k])] if st is not None), None)
            y = metric_stats(r.metrics["fid"]) if "fid" in r.metrics else None
            if x is None or y is None:
                notes.append(f"frontier_{family}: {t.id} row {r.id} has no finite fid and control_error; "
                             "point left out")
                continue
            out.setdefault(family, {}).setdefault(t.id, []).append((steps, x, y))
    for fam in out.values():
        for pts in fam.values():
            pts.sort(key=lambda p: p[0])
    return out


def paper_frontier(tables, family):
    """The paper's (steps, control_error, fid) points of a family from the tables' _paper rows; the
    paper's 'Generator only' row (anchorkv) is the RS0 point."""
    pts = {}
    for t in tables:
        if not t.id.startswith("anchorroute/table5"):
            continue
        for p in t.paper:
            m = PAPER_FRONTIER_ROW.match(p["ours_id"])
            steps = int(m.group(1)) if m else (0 if p["ours_id"] == "anchorkv" else None)
            v = p["values"]
            if (steps is None or not family_matches_section(family, p["section"])
                    or not all(np.isfinite(v.get(k, np.nan)) for k in ("fid", "control_error"))):
                continue
            pts[steps] = (v["control_error"], v["fid"])
    return sorted((s, x, y) for s, (x, y) in pts.items())


def draw_frontiers(tables, info, out, no_paper, written, notes):
    points = frontier_points(tables, notes)
    if not points:
        notes.append("frontier_*: no anchorroute/table5* or cross/* table with '<family>/rs<steps>' rows")
        return
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for family, by_table in sorted(points.items()):
        fig, ax = plt.subplots(figsize=(6.4, 4.8))
        for i, (tid, pts) in enumerate(sorted(by_table.items())):
            c = colors[i % len(colors)]
            xs = [p[1][0] for p in pts]
            ys = [p[2][0] for p in pts]
            counts = sorted({n for p in pts for n in (p[1][2], p[2][2])})
            n = str(counts[0]) if len(counts) == 1 else f"{counts[0]}-{counts[-1]}"
            bars = ax.errorbar(xs, ys, xerr=[p[1][1] for p in pts], yerr=[p[2][1] for p in pts], color=c,
                               marker="o", ms=6, lw=1.6, capsize=3, label=f"{tid} ({n} replicates)", zorder=3)
            bars.lines[0].set_gid("subject")
            for steps, x, y in pts:
                ax.annotate(f"RS{steps}", (x[0], y[0]), textcoords="offset points", xytext=(6, 5), fontsize=8,
                            color=c)
        paper = [] if no_paper else paper_frontier(tables, family)
        if paper:
            ax.plot([p[1] for p in paper], [p[2] for p in paper], color="0.4", ls="--", marker="o", mfc="white",
                    ms=6, lw=1.0, label="paper (Table V)", zorder=2)
            for steps, x, y in paper:
                ax.annotate(f"paper RS{steps}", (x, y), textcoords="offset points", xytext=(6, -11), fontsize=7,
                            color="0.4")
        ax.set_xlabel("control error (m), mean over replicates")
        ax.set_ylabel("FID, mean over replicates")
        ax.set_title(f"RouteSolver quality-control frontier: {family} anchors\n"
                     "(error bars: 95% CI over replicates; lower-left is better)", fontsize=10)
        ax.grid(alpha=0.3)
        ax.margins(0.15)
        ax.legend(fontsize=8, loc="best")
        footer(fig, info)
        fig.tight_layout(rect=(0, 0.02, 1, 1))
        save(fig, os.path.join(out, f"frontier_{safe_name(family)}.png"), written)


# --------------------------------------------------------------------------
# 2. ProjFlow Fig. 4: pelvis paths over the target path.

def informative_sample(rows):
    """The sample index shown for every row of a table (rows share their tasks): one with
    controlled entries if any, then the one whose ground-truth root travels farthest (a moving
    clip says more than a standing one; generated joints stand in when no target is stored),
    ties to the first."""
    k_max = min(len(e.lengths) for e in rows)
    best, best_key = 0, None
    for k in range(k_max):
        controlled = any(e.controlled[k, :int(e.lengths[k])].any() for e in rows)
        travels = []
        for e in rows:
            n = int(e.lengths[k])
            clip = e.target[k, :n] if np.abs(e.target[k, :n]).max() > 0 else e.joints[k, :n]
            root = clip[:, 0, [0, 2]]
            travels.append(float(np.linalg.norm(np.diff(root, axis=0), axis=-1).sum()) if n > 1 else 0.0)
        key = (controlled, float(np.median(travels)))
        if best_key is None or key > best_key:
            best, best_key = k, key
    return best


DIVERGED_FACTOR = 3.0  # a row whose view must be this many times the typical one is drawn on its own scale


def split_diverged(sizes):
    """Indices of the rows drawn on their own scale: those needing a view more than DIVERGED_FACTOR
    times the median row's (a diverged baseline must not shrink every other row to a dot)."""
    typical = float(np.median(sizes))
    return {i for i, v in enumerate(sizes) if v > DIVERGED_FACTOR * typical}


def square_view(points, margin=0.15, minimum=0.5):
    """(centre xz, half side) of a square view holding `points` [N, 2]."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    return (lo + hi) / 2, max(minimum, float((hi - lo).max()) / 2 * (1 + margin))


def draw_trajectory_overlay(examples, info, out, written, notes):
    rows = [e for e in examples.get("projflow/table1", []) if e.row_id.startswith("pelvis/")]
    if not rows:
        notes.append("trajectory_overlay: no /examples/projflow|table1 rows named 'pelvis|...'")
        return
    k = informative_sample(rows)
    paths = []
    for e in rows:
        n = int(e.lengths[k])
        paths.append((e, e.joints[k, :n, 0][:, [0, 2]], e.target[k, :n, 0][:, [0, 2]],
                      e.controlled[k, :n, 0].any(axis=-1)))
    # One view for the rows that follow the task, their own for the ones that ran away.
    views = [square_view(np.concatenate([g, t])) for _, g, t, _ in paths]
    diverged = split_diverged([v[1] for v in views])
    common = square_view(np.concatenate([np.concatenate([g, t]) for i, (_, g, t, _) in enumerate(paths)
                                         if i not in diverged]))
    panel = 3.6
    ncol = min(len(rows), max(4, math.ceil(len(rows) / 9)), int((render_motion.MAX_PX / DPI - 0.2) // panel))
    nrow = math.ceil(len(rows) / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(panel * ncol, (panel + 0.1) * nrow + 0.5), squeeze=False)
    for ax in axes.flat[len(rows):]:
        ax.set_visible(False)
    for i, (ax, (e, gen, tgt, ctrl)) in enumerate(zip(axes.flat, paths)):
        ax.plot(tgt[:, 0], tgt[:, 1], color=TARGET_COLOR, ls=":", lw=2.0, label="target path", zorder=1, gid="subject")
        ax.plot(gen[:, 0], gen[:, 1], color=GEN_COLOR, lw=1.8, label="generated pelvis", zorder=2, gid="subject")
        ax.scatter(tgt[ctrl, 0], tgt[ctrl, 1], s=14, facecolors="none", edgecolors="k", lw=0.8,
                   label="controlled frames", zorder=3)
        ax.plot(*gen[0], marker="o", color=GEN_COLOR, ms=5, zorder=4)
        ax.annotate("start", gen[0], textcoords="offset points", xytext=(4, 4), fontsize=7, color="0.3")
        err = np.linalg.norm(e.joints[k, :len(ctrl), 0] - e.target[k, :len(ctrl), 0], axis=-1)[ctrl]
        stat = f"pelvis error at controlled frames: {100 * err.mean():.2f} cm" if err.size else "no controlled frames"
        center, half = views[i] if i in diverged else common
        if i in diverged:
            stat += f"\nown scale ({2 * half:.0f} m across; others {2 * common[1]:.1f} m): diverged"
        ax.set_title(f"{wrap(e.label, 40)}\n{stat}", fontsize=8, color="#b00000" if i in diverged else "k")
        # x grows to the left: with z up the page this is the view from above (Y toward the reader),
        # so left turns look like left turns.
        ax.set_xlim(center[0] + half, center[0] - half)
        ax.set_ylim(center[1] - half, center[1] + half)
        ax.set_aspect("equal", adjustable="box")
        ax.set_xlabel("x (m), seen from above")
        ax.set_ylabel("z (m)")
        ax.grid(alpha=0.3)
    axes.flat[0].legend(fontsize=7, loc="best")
    e0 = rows[0]
    fig.suptitle(wrap(f"Pelvis trajectory control (sample {k}): \"{e0.caption(k)}\"", 110), fontsize=10)
    footer(fig, info)
    fig.tight_layout(rect=(0, 0.02, 1, 0.97))
    save(fig, os.path.join(out, "trajectory_overlay.png"), written)


# --------------------------------------------------------------------------
# 3. ProjFlow Fig. 5: 2D-to-3D lifting example.

def draw_bones_2d(ax, pts, parents, **kw):
    for c, p in enumerate(parents):
        if p >= 0:
            ax.plot([pts[p, 0], pts[c, 0]], [pts[p, 1], pts[c, 1]], **kw)


def draw_lifting(examples, skeleton, info, out, written, notes):
    rows = examples.get("projflow/table2", [])
    if not rows:
        notes.append("lifting_example: no /examples/projflow|table2")
        return
    e = rows[0]
    if e.camera is None or e.controlled_2d is None:
        notes.append(f"lifting_example: /examples/projflow|table2 row {e.row_id} has no camera or controlled_2d")
        return
    usable = [k for k in range(len(e.lengths)) if np.isfinite(e.camera[k]).all() and e.camera[k, 0] > 0]
    if not usable:
        notes.append(f"lifting_example: /examples/projflow|table2 row {e.row_id}: no sample has a valid camera")
        return
    if skeleton is None or len(skeleton["parents"]) != e.joints.shape[2]:
        notes.append("lifting_example: /skeleton is missing or does not match the joint count of the examples")
        return
    k = usable[0]
    n = int(e.lengths[k])
    cam = e.camera[k]
    gen, tgt, obs = e.joints[k, :n], e.target[k, :n], e.controlled_2d[k, :n]
    gen2, tgt2 = project(gen, cam), project(tgt, cam)
    parents, names = skeleton["parents"], skeleton["names"]
    bone_col = render_motion.bone_colors({"names": names})

    fig = plt.figure(figsize=(12.5, 5.6))
    ax2 = fig.add_subplot(1, 2, 1)
    # Frames where most joints are observed are key poses (the initial 2D keypose of Sketch2Anim).
    for i, t in enumerate(np.flatnonzero(obs.sum(axis=1) >= max(2, obs.shape[1] // 2))):
        draw_bones_2d(ax2, tgt2[t], parents, color=TARGET_COLOR, lw=2.2, ls="--", zorder=1)
        draw_bones_2d(ax2, gen2[t], parents, color=GEN_COLOR, lw=1.2, zorder=2, gid="subject")
        top = tgt2[t, np.argmax(tgt2[t, :, 1])]
        ax2.annotate(f"key pose t={t}", top, textcoords="offset points", xytext=(0, 6), fontsize=7,
                     color="0.3", ha="center")
        if i == 0:
            ax2.plot([], [], color=TARGET_COLOR, lw=2.2, ls="--", label="2D key pose (target)")
            ax2.plot([], [], color=GEN_COLOR, lw=1.2, label="key pose, generated, projected")
    traj_joints = [j for j in range(obs.shape[1]) if obs[:, j].sum() >= 2]
    cmap = plt.get_cmap("tab10")
    for i, j in enumerate(traj_joints[:10]):
        c = cmap(i % 10)
        ts = np.flatnonzero(obs[:, j])
        ax2.plot(gen2[:, j, 0], gen2[:, j, 1], color=c, lw=1.6, zorder=3, label=f"{names[j]}: generated, projected",
                 gid="subject")
        ax2.scatter(tgt2[ts, j, 0], tgt2[ts, j, 1], s=16, marker="x", color="k", lw=0.8, zorder=4,
                    label="2D targets" if i == 0 else None)
    if len(traj_joints) > 10:
        notes.append(f"lifting_example: drew 10 of {len(traj_joints)} observed joint trajectories")
    err = np.linalg.norm(gen2 - tgt2, axis=-1)[obs]
    ax2.set_title(f"2D view through the known camera (s={cam[0]:.2f}, pitch={cam[1]:.0f}, yaw={cam[2]:.0f}, "
                  f"roll={cam[3]:.0f} deg)\nmean 2D error at observed points: {100 * err.mean():.2f} cm",
                  fontsize=9)
    ax2.set_aspect("equal", adjustable="datalim")
    ax2.set_xlabel("image u (m x scale)")
    ax2.set_ylabel("image v (m x scale)")
    ax2.grid(alpha=0.3)
    ax2.legend(fontsize=7, loc="best")

    ax3 = fig.add_subplot(1, 2, 2, projection="3d")
    # Matplotlib's vertical axis is its third; (x, -z, y) keeps the world right-handed with Y up.
    px, py, pz = gen[..., 0], -gen[..., 2], gen[..., 1]
    shown = render_motion.strip_frames(n, 5)
    for i, t in enumerate(shown):
        alpha = 0.35 + 0.65 * (i + 1) / len(shown)
        for c, p in enumerate(parents):
            if p >= 0:
                ax3.plot([px[t, p], px[t, c]], [py[t, p], py[t, c]], [pz[t, p], pz[t, c]], color=bone_col[c],
                         lw=1.8, alpha=alpha, gid="subject")
        ax3.text(px[t, 0], py[t, 0], pz[t].max() + 0.08, f"t={t}", fontsize=7, color="0.3")
    floor = min(0.0, float(pz.min()))
    ax3.plot(px[:, 0], py[:, 0], np.full(n, floor), color="0.55", lw=1.0)
    mid = np.array([(px.max() + px.min()) / 2, (py.max() + py.min()) / 2, (pz.max() + floor) / 2])
    half = max(px.max() - px.min(), py.max() - py.min(), pz.max() - floor) / 2 + 0.1
    ax3.set_xlim(mid[0] - half, mid[0] + half)
    ax3.set_ylim(mid[1] - half, mid[1] + half)
    ax3.set_zlim(mid[2] - half, mid[2] + half)
    ax3.set_box_aspect((1, 1, 1))
    ax3.set_xlabel("x (m)", fontsize=8)
    ax3.set_ylabel("-z (m)", fontsize=8)
    ax3.set_zlabel("y (m)", fontsize=8)
    ax3.tick_params(labelsize=7)
    ax3.set_title("generated 3D motion (later frames darker; blue = left, red = right)", fontsize=9)
    fig.suptitle(wrap(f"2D-to-3D lifting, {e.label}, sample {k}: \"{e.caption(k)}\"", 120), fontsize=10)
    footer(fig, info)
    fig.tight_layout(rect=(0, 0.02, 1, 0.95))
    save(fig, os.path.join(out, "lifting_example.png"), written)


# --------------------------------------------------------------------------
# 4. Training curves.

def plain_log_labels(ax):
    """Plain-number labels on a log y axis (the default ones are mathtext, switched off above); on a
    short range the 2x and 5x minor ticks are labelled too."""
    lo, hi = ax.get_ylim()
    short = math.log10(hi / lo) < 2.0
    ax.yaxis.set_major_formatter(ticker.FuncFormatter(lambda v, _: f"{v:g}"))

    def minor(v, _):
        mantissa = round(v / 10 ** math.floor(math.log10(v) + 1e-9))
        return f"{v:g}" if short and mantissa in (2, 5) else ""
    ax.yaxis.set_minor_formatter(ticker.FuncFormatter(minor))


def draw_training(f, path, info, out, written, notes):
    if "training" not in f or not isinstance(f["training"], h5py.Group) or not len(f["training"]):
        notes.append("training_curves: no /training group")
        return
    comps = []
    for name, g in f["training"].items():
        if not isinstance(g, h5py.Group):
            continue
        cols = {decode_name(c): read_vector(f, f"training/{name}/{c}", path)
                for c, ds in g.items() if isinstance(ds, h5py.Dataset)}
        if "step" not in cols or "loss" not in cols:
            notes.append(f"training_curves: /training/{name} has no 'step' or 'loss' column; left out")
            continue
        if any(len(v) != len(cols["step"]) for v in cols.values()):
            raise ResultsError(f"{path}: /training/{name}: columns differ in length")
        comps.append((decode_name(name), attr_str(g.attrs, "run_dir"), cols))
    if not comps:
        notes.append("training_curves: no /training component with step and loss")
        return
    # Fixed 5.0 x 3.8 in panels, three to a row; a page holds as many rows as fit in MAX_PX.
    ncol = min(3, len(comps))
    per_page = ncol * max(1, int((render_motion.MAX_PX / DPI - 0.6) // 3.8))
    pages = [comps[i:i + per_page] for i in range(0, len(comps), per_page)]
    for page_no, page in enumerate(pages):
        nrow = math.ceil(len(page) / ncol)
        fig, axes = plt.subplots(nrow, ncol, figsize=(5.0 * ncol, 3.8 * nrow + 0.5), squeeze=False)
        for ax in axes.flat[len(page):]:
            ax.set_visible(False)
        for ax, (name, run_dir, cols) in zip(axes.flat, page):
            step = cols["step"]
            parts = ["loss"] + sorted(c for c in cols if c not in NOT_LOSS_COLUMNS and c != "loss")
            drawn = 0
            for c in parts:
                v = np.where(np.isfinite(cols[c]) & (cols[c] > 0), cols[c], np.nan)  # log axis: positive only
                if np.isnan(v).all():
                    continue
                main = c == "loss"
                ax.plot(step, v, lw=2.0 if main else 1.0, color="k" if main else None,
                        alpha=1.0 if main else 0.85, label=c, zorder=3 if main else 2, gid="subject")
                drawn += 1
            if drawn:
                ax.set_yscale("log")
                plain_log_labels(ax)
            ax.set_title(f"{name}\n{textwrap.shorten(run_dir, 60)}" if run_dir else name, fontsize=9)
            ax.set_xlabel("step")
            ax.set_ylabel("loss (log)")
            ax.grid(alpha=0.3, which="both")
            ax.legend(fontsize=7, loc="best")
        more = f" (part {page_no + 1} of {len(pages)})" if len(pages) > 1 else ""
        fig.suptitle(f"Training losses (mean over each logging interval){more}", fontsize=10)
        footer(fig, info)
        fig.tight_layout(rect=(0, 0.02, 1, 0.97))
        suffix = f"_{page_no + 1}" if page_no else ""
        save(fig, os.path.join(out, f"training_curves{suffix}.png"), written)


# --------------------------------------------------------------------------
# 5. Stick-figure strips, one figure per examples table.

def snap_to_controlled(shown, controlled_frames, length):
    """Move each evenly spaced strip frame to the nearest controlled frame within half a spacing, so
    sparse constraints (a few keyframes) appear in the strip; frames stay distinct and sorted."""
    if len(shown) < 2 or not len(controlled_frames):
        return shown
    half = (length - 1) / (len(shown) - 1) / 2
    out = []
    for t in shown:
        near = controlled_frames[np.argmin(np.abs(controlled_frames - t))]
        pick = int(near) if abs(near - t) <= half and near not in out else int(t)
        out.append(pick if pick not in out else int(t))
    return np.array(sorted(set(out)))


STRIP_HEAD_IN, STRIP_BLOCK_TITLE_IN, STRIP_LEFT_IN, STRIP_BLOCK_GAP_IN = 0.75, 0.42, 0.5, 0.3
STRIP_ROWS_PER_COLUMN = 8  # strips stacked before a second column of strips starts


def strip_pages(n_rows, block_w, block_h, head, foot):
    """Blocks (one strip each) laid out in columns then pages so that no figure exceeds MAX_PX:
    [(first, count, columns, rows per column)]. Columns are added before the figure grows past
    STRIP_ROWS_PER_COLUMN strips; pages only when even the widest grid is full."""
    limit = render_motion.MAX_PX / DPI
    max_cols = max(1, int((limit - 0.1) // block_w))
    max_rows = max(1, int((limit - head - foot) // block_h))
    pages, first = [], 0
    while first < n_rows:
        left = n_rows - first
        cols = min(max_cols, max(1, math.ceil(left / STRIP_ROWS_PER_COLUMN)))
        per_col = min(max_rows, math.ceil(left / cols))
        count = min(left, cols * per_col)
        cols = math.ceil(count / per_col)
        pages.append((first, count, cols, per_col))
        first += count
    return pages


def draw_strips(examples, skeleton, info, out, frames, fps, written, notes):
    if not examples:
        notes.append("strips_*: no /examples group")
        return
    if skeleton is None:
        notes.append("strips_*: no /skeleton group, so no bones to draw")
        return
    parents = skeleton["parents"]
    colors = render_motion.bone_colors({"names": skeleton["names"]})
    pw, ph = render_motion.PANEL_W_IN, render_motion.PANEL_H_IN
    pt, gap = render_motion.PANEL_TITLE_IN, render_motion.PANEL_GAP_IN
    for tid, rows in sorted(examples.items()):
        if not rows:
            continue
        if any(e.joints.shape[2] != len(parents) for e in rows):
            notes.append(f"strips_{safe_name(tid)}: examples have {rows[0].joints.shape[2]} joints, "
                         f"/skeleton {len(parents)}")
            continue
        k = informative_sample(rows)
        clips = [e.joints[k, :int(e.lengths[k])] for e in rows]
        views = [render_motion.view_axis(c) for c in clips]
        # Each row fitted to the fixed panel; rows share the scale of the typical row unless
        # they need far more room (diverged), which get their own and say so.
        own = [render_motion.fit_extent(render_motion.strip_extent(c, u)) for c, u in zip(clips, views)]
        diverged = split_diverged([render_motion.extent_size(x) for x in own])
        normal = [x for i, x in enumerate(own) if i not in diverged]
        shared = (max(x[0] for x in normal), min(x[1] for x in normal), max(x[2] for x in normal))
        shared = render_motion.fit_extent(shared)
        ncol = min(frames, max(len(c) for c in clips))
        per_line, lines = render_motion.panel_lines(ncol)
        block_w = STRIP_LEFT_IN + per_line * (pw + gap) + STRIP_BLOCK_GAP_IN
        block_h = STRIP_BLOCK_TITLE_IN + lines * (ph + pt + gap) + 0.1
        pages = strip_pages(len(rows), block_w, block_h, STRIP_HEAD_IN, 0.25)
        for page_no, (first, count, cols, per_col) in enumerate(pages):
            fig_w = cols * block_w + 0.1
            fig_h = STRIP_HEAD_IN + per_col * block_h + 0.25
            fig = plt.figure(figsize=(fig_w, fig_h), dpi=DPI)
            for slot in range(count):
                r = first + slot
                e, clip, u = rows[r], clips[r], views[r]
                left = (slot // per_col) * block_w + STRIP_LEFT_IN
                top = STRIP_HEAD_IN + (slot % per_col) * block_h + STRIP_BLOCK_TITLE_IN
                axes = render_motion.strip_axes(fig, left, top, per_line, lines, fig_w, fig_h)
                n = len(clip)
                ctrl = e.controlled[k, :n].any(axis=-1)                     # [T, J]
                shown = snap_to_controlled(render_motion.strip_frames(n, ncol), np.flatnonzero(ctrl.any(axis=1)), n)
                for ax in axes[len(shown):]:
                    ax.set_visible(False)
                # The ground-truth clip the task came from, faint behind the sample, and the hard 3D
                # constraints of the shown frame (targets of the controlled joints).
                th, tv, td = render_motion.side_view(e.target[k, :n], u)
                for ax, t in zip(axes, shown):
                    render_motion.draw_pose(ax, th[t], tv[t], td[t], parents, ["0.8"] * len(parents), lw=1.4,
                                            zorder=1.5, subject=False)
                    cj = np.flatnonzero(ctrl[t])
                    if cj.size:
                        ax.scatter(th[t, cj], tv[t, cj], s=30, facecolors="none", edgecolors="k", lw=0.9, zorder=4)
                extent = "per_panel" if r in diverged else shared
                render_motion.draw_strip(axes[:len(shown)], clip, parents, colors, shown, fps, u, extent,
                                         ylabel_axes=[axes[i * per_line] for i in range(lines)])
                title = f"{e.label}: \"{e.caption(k)}\""
                width = int(12 * (block_w - STRIP_BLOCK_GAP_IN))
                color = "k"
                if r in diverged:
                    title = textwrap.shorten(title, width=max(20, width - 60))
                    title += (f"  [diverged: needs a {render_motion.extent_size(own[r]):.0f} m view, the others "
                              f"{render_motion.extent_size(shared):.1f} m; each panel zoomed to its own pose]")
                    color = "#b00000"
                else:
                    title = textwrap.shorten(title, width=width)
                fig.text((left - STRIP_LEFT_IN + 0.1) / fig_w, 1.0 - (top - STRIP_BLOCK_TITLE_IN + 0.08) / fig_h,
                         title, fontsize=8.5, fontweight="bold", ha="left", va="top", color=color)
            more = f" (part {page_no + 1} of {len(pages)})" if len(pages) > 1 else ""
            fig.suptitle(f"{tid}: sample {k} of each row{more}\n(grey: ground-truth clip; circles: controlled "
                         "joints at that frame; blue = left, red = right; one scale unless marked)",
                         fontsize=9, y=1.0 - 0.08 / fig_h, va="top")
            footer(fig, info)
            suffix = f"_{page_no + 1}" if page_no else ""
            save(fig, os.path.join(out, f"strips_{safe_name(tid)}{suffix}.png"), written)


# --------------------------------------------------------------------------

def main(argv=None):
    args = parse_args(sys.argv[1:] if argv is None else argv)
    written, notes = [], []
    MANIFEST.clear()
    MANIFEST["enabled"] = bool(args.manifest)
    try:
        with open_results(args.file) as f:
            tables = read_tables(f, args.file)
            skeleton = read_skeleton(f, args.file)
            labels = row_labels(tables)
            examples = {}
            if "examples" in f and isinstance(f["examples"], h5py.Group):
                for tname, g in f["examples"].items():
                    if isinstance(g, h5py.Group):
                        examples[decode_name(tname)] = read_examples(f, args.file, tname, labels)
            info = (f"{os.path.basename(args.file)}  profile={attr_str(f.attrs, 'profile') or '?'}  "
                    f"commit={attr_str(f.attrs, 'commit') or '?'}")
            try:
                os.makedirs(args.out, exist_ok=True)
            except OSError as e:
                raise ResultsError(f"{args.out}: cannot create output folder ({e.strerror})") from None
            draw_frontiers(tables, info, args.out, args.no_paper, written, notes)
            draw_trajectory_overlay(examples, info, args.out, written, notes)
            draw_lifting(examples, skeleton, info, args.out, written, notes)
            draw_training(f, args.file, info, args.out, written, notes)
            fps = float(f.attrs["fps"]) if "fps" in f.attrs else DEFAULT_FPS
            draw_strips(examples, skeleton, info, args.out, args.frames, fps, written, notes)
    except (ResultsError, motionio.MotionFileError) as e:
        motionio.fail(str(e))
    if args.manifest:
        def write_manifest(tmp):
            with open(tmp, "w") as fh:
                json.dump(MANIFEST.get("figures", {}), fh, indent=1)
        motionio.atomic_output(args.manifest, write_manifest)
    for path in written:
        print(path)
    for note in notes:
        print(f"skipped: {note}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
