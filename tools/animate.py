#!/usr/bin/python3
"""Animate clips of any motion file (a `generate` or `sample` output, a dataset) to MP4 (Debian's
ffmpeg) and GIF: the motion in 3D on a floor grid, the constraint targets it was generated under
(keyframes, trajectories, planar paths, 2D observations in their camera), the source clip beside it
when given, and a top-down view of the paths."""

import argparse
import os
import shutil
import sys
import textwrap

import numpy as np
import matplotlib

matplotlib.use("Agg")
matplotlib.rcParams["text.parse_math"] = False  # captions and ids may contain "$"
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib import animation  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import motionio  # noqa: E402
import render_motion  # noqa: E402
import figures  # noqa: E402

GEN_COLOR, SOURCE_COLOR, TARGET_COLOR = "#ff7f0e", "0.45", "#2ca02c"
PANEL_IN = 4.0          # each panel is PANEL_IN x PANEL_IN inches
MP4_DPI, GIF_DPI = 100, 60
GIF_FPS = 10.0
KEY_HALO = 2            # a keyframe target is highlighted this many frames either side of its frame


def parse_args(argv):
    p = argparse.ArgumentParser(
        description="Animate motion clips to MP4/GIF with their constraint targets.",
        epilog="Example: animate.py samples/keyframes_smoke.h5 --out anim --source data/fixture_smoke.h5 --count 2")
    p.add_argument("file", help="motion file (.h5): a generate/sample output or a dataset")
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    sel = p.add_mutually_exclusive_group()
    sel.add_argument("--clips", help="comma-separated clip indices, e.g. 0,3")
    sel.add_argument("--ids", help="comma-separated clip ids")
    sel.add_argument("--all", action="store_true", help="every clip of the file")
    p.add_argument("--count", type=int, default=1, help="without --clips/--ids/--all: the first COUNT clips (1)")
    p.add_argument("--source", help="motion file holding the clips the samples came from (drawn beside them); "
                                    "matched by id, a generate sample '<clip id>#<task>' to clip '<clip id>'")
    p.add_argument("--format", default="mp4,gif",
                   help="comma-separated: mp4 (needs ffmpeg), gif (default: both)")
    p.add_argument("--crf", type=int, default=30, help="x264 quality for MP4, 18 (large) .. 40 (small); default 30")
    args = p.parse_args(argv)
    args.formats = [x.strip() for x in args.format.split(",") if x.strip()]
    bad = [x for x in args.formats if x not in ("mp4", "gif")]
    if bad or not args.formats:
        p.error(f"--format takes mp4 and/or gif, got {args.format!r}")
    if args.count < 1:
        p.error("--count must be >= 1")
    if not 0 <= args.crf <= 51:
        p.error("--crf must be in 0..51")
    return args


def select(motion, args):
    if args.all:
        return list(range(motion.num_clips))
    if args.clips or args.ids:
        ns = argparse.Namespace(clips=args.clips, ids=args.ids, count=args.count)
        return render_motion.select_clips(motion, ns)
    return list(range(min(args.count, motion.num_clips)))


def source_clip(source, clip_id):
    """The source clip of sample `clip_id`: the same id, else the id before '#<task>'."""
    lookup = {cid: i for i, cid in enumerate(source.ids)}
    for key in (clip_id, clip_id.rsplit("#", 1)[0]):
        if key in lookup:
            return source.clip(lookup[key]).astype(np.float64)
    return None


class Targets:
    """What one sample was constrained to, sorted for drawing."""

    def __init__(self, items, length):
        self.points = []     # (frame, joint, xyz): fully given 3D targets
        self.paths = []      # (joint, frames, xyz [F, 3]) of dense 3D targets (trajectories), drawn as lines
        self.floor = []      # (frames, xz [F, 2]): targets on x and z only (planar paths, xz keyframes)
        self.cameras = []    # (camera [4], frames, joints, uv [F, Jk, 2])
        self.notes = []      # what is not drawn (relative offsets, loops)
        for it in items:
            kind, frames, joints, v = it["type"], it["frames"], it["joints"], it["values"]
            if kind in ("keyframe", "trajectory") and v is not None:
                v = v.reshape(len(frames), len(joints), len(it["axes"]))
                if it["axes"] == [0, 1, 2]:
                    for fi, t in enumerate(frames):
                        for ji, j in enumerate(joints):
                            self.points.append((int(t), j, v[fi, ji]))
                    if len(frames) > 5:
                        for ji, j in enumerate(joints):
                            self.paths.append((j, frames, v[:, ji]))
                elif 0 in it["axes"] and 2 in it["axes"]:
                    ax = [it["axes"].index(0), it["axes"].index(2)]
                    for ji in range(len(joints)):
                        self.floor.append((frames, v[:, ji][:, ax]))
                else:
                    self.notes.append(f"{kind} on axes {it['axes']}")
            elif kind == "planar_root" and v is not None:
                self.floor.append((frames, v.reshape(len(frames), 2)))
            elif kind == "camera_2d" and v is not None and it["camera"] is not None:
                self.cameras.append((it["camera"], frames, joints, v.reshape(len(frames), len(joints), 2)))
            else:
                self.notes.append(kind)
        self.length = length

    def xz(self):
        pts = [p[2][[0, 2]] for p in self.points] + [f[1] for f in self.floor]
        return np.concatenate([np.atleast_2d(p) for p in pts]) if pts else np.zeros((0, 2))


class Body3D:
    """One 3D panel: a skeleton following its root, a floor grid fixed in the world, the root's trail
    and the 3D targets. Matplotlib 3D axes do not clip, so everything is kept inside the window."""

    def __init__(self, fig, rect, clip, skeleton, title, targets=None, color_bones=True):
        self.clip, self.parents = clip, skeleton["parents"]
        self.ax = fig.add_axes(rect, projection="3d")
        ax = self.ax
        # Matplotlib's vertical axis is its third; plotting (x, -z, y) keeps the world right-handed, Y up.
        self.p = np.stack([clip[..., 0], -clip[..., 2], clip[..., 1]], axis=-1)
        reach = np.hypot(self.p[..., 0] - self.p[:, :1, 0], self.p[..., 1] - self.p[:, :1, 1]).max()
        self.floor = min(0.0, float(self.p[..., 2].min()))
        self.half = max(1.0, reach + 0.3, (float(self.p[..., 2].max()) - self.floor + 0.1) / 2)
        self.spacing = 0.5
        n_grid = int(np.ceil(2 * self.half / self.spacing)) + 2
        ax.set_zlim(self.floor, self.floor + 2 * self.half)
        ax.set_box_aspect((1, 1, 1))
        ax.set_xlabel("x", fontsize=7)
        ax.set_ylabel("-z", fontsize=7)
        ax.set_zlabel("y", fontsize=7)
        ax.tick_params(labelsize=6)
        ax.set_title(title, fontsize=9)
        self.grid = [ax.plot([], [], [], color="0.82", lw=0.6)[0] for _ in range(2 * n_grid)]
        self.trail = ax.plot([], [], [], color="0.55", lw=0.9, alpha=0.7)[0]
        colors = render_motion.bone_colors(skeleton) if color_bones else ["0.35"] * len(self.parents)
        self.bones = {c: ax.plot([], [], [], color=colors[c], lw=2.2)[0]
                      for c in range(len(self.parents)) if self.parents[c] >= 0}
        self.targets = targets
        self.target_dots = ax.plot([], [], [], ls="none", marker="o", ms=4, mfc="none", mec=TARGET_COLOR,
                                   mew=1.0)[0]
        self.active = ax.plot([], [], [], ls="none", marker="o", ms=9, color=TARGET_COLOR, alpha=0.85)[0]
        self.links = ax.plot([], [], [], color=TARGET_COLOR, lw=1.2, ls="--")[0]
        self.paths = [ax.plot([], [], [], color=TARGET_COLOR, lw=1.0, ls=":")[0]
                      for _ in (targets.paths if targets else [])]

    def _inside(self, pts, lo, hi):
        return (pts[:, 0] >= lo[0]) & (pts[:, 0] <= hi[0]) & (pts[:, 1] >= lo[1]) & (pts[:, 1] <= hi[1])

    def update(self, t):
        ax, p, half, sp = self.ax, self.p, self.half, self.spacing
        t = min(t, len(p) - 1)
        lo = np.array([p[t, 0, 0] - half, p[t, 0, 1] - half])
        hi = lo + 2 * half
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        n = len(self.grid) // 2
        for k in range(n):
            gx = np.ceil(lo[0] / sp) * sp + k * sp
            gy = np.ceil(lo[1] / sp) * sp + k * sp
            self.grid[k].set_data_3d(*(([gx, gx], [lo[1], hi[1]], [self.floor] * 2) if gx <= hi[0] else ([], [], [])))
            self.grid[n + k].set_data_3d(*(([lo[0], hi[0]], [gy, gy], [self.floor] * 2) if gy <= hi[1]
                                           else ([], [], [])))
        root = p[:t + 1, 0]
        keep = self._inside(root, lo, hi)
        self.trail.set_data_3d(np.where(keep, root[:, 0], np.nan), np.where(keep, root[:, 1], np.nan),
                               np.full(len(root), self.floor))
        for c, line in self.bones.items():
            q = self.parents[c]
            line.set_data_3d([p[t, q, 0], p[t, c, 0]], [p[t, q, 1], p[t, c, 1]], [p[t, q, 2], p[t, c, 2]])
        if self.targets is None:
            return
        pts = [(f, j, np.array([v[0], -v[2], v[1]])) for f, j, v in self.targets.points]
        all_xyz = np.array([q for _, _, q in pts]).reshape(-1, 3)
        if len(all_xyz):
            inside = self._inside(all_xyz, lo, hi)
            self.target_dots.set_data_3d(all_xyz[inside, 0], all_xyz[inside, 1], all_xyz[inside, 2])
        now = [(j, q) for f, j, q in pts if abs(f - t) <= KEY_HALO and f < len(p)]
        now_xyz = np.array([q for _, q in now]).reshape(-1, 3)
        inside = self._inside(now_xyz, lo, hi) if len(now_xyz) else np.zeros(0, bool)
        self.active.set_data_3d(now_xyz[inside, 0], now_xyz[inside, 1], now_xyz[inside, 2])
        lx, ly, lz = [], [], []
        for (j, q), ok in zip(now, inside):
            if ok:
                lx += [p[t, j, 0], q[0], np.nan]
                ly += [p[t, j, 1], q[1], np.nan]
                lz += [p[t, j, 2], q[2], np.nan]
        self.links.set_data_3d(lx, ly, lz)
        for line, (j, frames, xyz) in zip(self.paths, self.targets.paths):
            q = np.stack([xyz[:, 0], -xyz[:, 2], xyz[:, 1]], axis=-1)
            ok = self._inside(q, lo, hi)
            line.set_data_3d(np.where(ok, q[:, 0], np.nan), np.where(ok, q[:, 1], np.nan),
                             np.where(ok, q[:, 2], np.nan))


class TopDown:
    """The paths seen from above (x grows to the left, as in tools/figures.py): the root of the sample and
    of its source, the targets on the floor, and where each is now."""

    def __init__(self, fig, rect, clip, source, targets):
        self.ax = ax = fig.add_axes(rect)
        self.clip, self.source = clip, source
        pts = [clip[:, 0][:, [0, 2]]] + ([source[:, 0][:, [0, 2]]] if source is not None else []) + [targets.xz()]
        center, half = figures.square_view(np.concatenate(pts))
        if source is not None:
            ax.plot(source[:, 0, 0], source[:, 0, 2], color=SOURCE_COLOR, lw=1.2, ls="--", label="source root")
        ax.plot(clip[:, 0, 0], clip[:, 0, 2], color=GEN_COLOR, lw=1.5, label="root")
        tp = np.array([[v[0], v[2]] for _, _, v in targets.points]).reshape(-1, 2)
        if len(tp):
            ax.scatter(tp[:, 0], tp[:, 1], s=22, facecolors="none", edgecolors=TARGET_COLOR, lw=1.0,
                       label="3D targets", zorder=3)
        for k, (frames, xz) in enumerate(targets.floor):
            ax.plot(xz[:, 0], xz[:, 1], ls="none", marker="x", ms=4, color=TARGET_COLOR,
                    label="xz targets" if k == 0 else None, zorder=3)
        self.now = ax.plot([], [], marker="o", ms=7, color=GEN_COLOR, ls="none", zorder=4)[0]
        self.now_src = ax.plot([], [], marker="o", ms=6, color=SOURCE_COLOR, ls="none", zorder=4)[0]
        ax.set_xlim(center[0] + half, center[0] - half)
        ax.set_ylim(center[1] - half, center[1] + half)
        ax.set_aspect("equal", adjustable="box")
        ax.grid(alpha=0.3)
        ax.set_title("from above (x to the left, z up)", fontsize=9)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=7, loc="best")

    def update(self, t):
        c = self.clip[min(t, len(self.clip) - 1), 0]
        self.now.set_data([c[0]], [c[2]])
        if self.source is not None:
            s = self.source[min(t, len(self.source) - 1), 0]
            self.now_src.set_data([s[0]], [s[2]])


class CameraView:
    """The sample seen through the camera of its 2D observations, with the 2D targets."""

    def __init__(self, fig, rect, clip, skeleton, camera_items):
        self.ax = ax = fig.add_axes(rect)
        cam = camera_items[0][0]
        self.uv = figures.project(clip, cam)                               # [T, J, 2]
        self.parents = parents = skeleton["parents"]
        self.items = camera_items
        allt = np.concatenate([it[3].reshape(-1, 2) for it in camera_items] + [self.uv.reshape(-1, 2)])
        center, half = figures.square_view(allt, minimum=0.3)
        ax.set_xlim(center[0] - half, center[0] + half)
        ax.set_ylim(center[1] - half, center[1] + half)
        ax.set_aspect("equal", adjustable="box")
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
        ax.set_title(f"camera view (s={cam[0]:.2f}, pitch {cam[1]:.0f}, yaw {cam[2]:.0f})", fontsize=9)
        colors = render_motion.bone_colors(skeleton)
        self.bones = {c: ax.plot([], [], color=colors[c], lw=2.0)[0] for c in range(len(parents)) if parents[c] >= 0}
        for cam_i, frames, joints, uv in camera_items:
            if len(frames) > 1:
                for ji in range(len(joints)):
                    ax.plot(uv[:, ji, 0], uv[:, ji, 1], ls="none", marker=".", ms=2, color=TARGET_COLOR)
        self.active = ax.plot([], [], ls="none", marker="x", ms=7, mew=1.5, color=TARGET_COLOR,
                              label="2D targets now")[0]
        ax.legend(fontsize=7, loc="best")

    def update(self, t):
        t = min(t, len(self.uv) - 1)
        for c, line in self.bones.items():
            q = self.parents[c]
            line.set_data([self.uv[t, q, 0], self.uv[t, c, 0]], [self.uv[t, q, 1], self.uv[t, c, 1]])
        now = [uv[np.flatnonzero(frames == t)[0]] for _, frames, _, uv in self.items if t in frames]
        now = np.concatenate(now) if now else np.zeros((0, 2))
        self.active.set_data(now[:, 0], now[:, 1])


def build_figure(motion, i, clip, source, targets):
    panels = ["sample"] + (["source"] if source is not None else []) + \
             (["camera"] if targets.cameras else []) + ["top"]
    n = len(panels)
    head = 0.7
    fig = plt.figure(figsize=(PANEL_IN * n, PANEL_IN + head))
    w, h = 1.0 / n, PANEL_IN / (PANEL_IN + head)
    views = []
    for k, kind in enumerate(panels):
        rect = (k * w + 0.01, 0.02, w - 0.02, h - 0.04)
        if kind == "sample":
            views.append(Body3D(fig, rect, clip, motion.skeleton, "sample, with its targets (green)", targets))
        elif kind == "source":
            views.append(Body3D(fig, rect, source, motion.skeleton, "source clip", targets, color_bones=False))
        elif kind == "camera":
            views.append(CameraView(fig, rect, clip, motion.skeleton, targets.cameras))
        else:
            views.append(TopDown(fig, rect, clip, source, targets))
    caption = textwrap.shorten(motion.captions[i][0], width=int(14 * PANEL_IN * n))
    fig.text(0.01, 1 - 0.12 / (PANEL_IN + head), caption, fontsize=10, va="top", ha="left")
    extra = f"; not drawn: {', '.join(sorted(set(targets.notes)))}" if targets.notes else ""
    counter = fig.text(0.01, 1 - 0.42 / (PANEL_IN + head), "", fontsize=8, va="top", ha="left", color="0.3")

    def update(t):
        for v in views:
            v.update(t)
        counter.set_text(f"{motion.ids[i]}  frame {t + 1}/{len(clip)}  ({t / motion.fps:.2f} s); "
                         f"green: constraint targets (filled near their frame){extra}")
        return []
    return fig, update


def render_clip(motion, i, source, items, out_stem, formats, crf):
    clip = motion.clip(i).astype(np.float64)
    targets = Targets(items, len(clip))
    written = []
    for fmt in formats:
        fig, update = build_figure(motion, i, clip, source, targets)
        if fmt == "mp4":
            frames = np.arange(len(clip))
            writer = animation.FFMpegWriter(fps=motion.fps, codec="libx264",
                                            extra_args=["-pix_fmt", "yuv420p", "-crf", str(crf),
                                                        "-preset", "slow"])
            dpi = MP4_DPI
        else:
            step = max(1, int(round(motion.fps / GIF_FPS)))
            frames = np.arange(0, len(clip), step)
            writer = animation.PillowWriter(fps=motion.fps / step)
            dpi = GIF_DPI
        anim = animation.FuncAnimation(fig, update, frames=frames, blit=False)
        path = f"{out_stem}.{fmt}"
        motionio.atomic_output(path, lambda tmp: anim.save(tmp, writer=writer, dpi=dpi), suffix="." + fmt)
        plt.close(fig)
        written.append(path)
    return written


def main(argv=None):
    args = parse_args(sys.argv[1:] if argv is None else argv)
    try:
        if "mp4" in args.formats and shutil.which("ffmpeg") is None:
            raise motionio.MotionFileError("ffmpeg is not installed, so no MP4 can be written: install Debian's "
                                           "ffmpeg (apt-get install ffmpeg) or pass --format gif")
        motion = motionio.read_motion(args.file)
        chosen = select(motion, args)
        control = motionio.read_control(args.file, motion)
        source = motionio.read_motion(args.source) if args.source else None
        if source is not None and source.skeleton["names"] != motion.skeleton["names"]:
            raise motionio.MotionFileError(f"{args.source}: its skeleton differs from {args.file}'s; pass the "
                                           "dataset the samples were generated from")
        try:
            os.makedirs(args.out, exist_ok=True)
        except OSError as e:
            raise motionio.MotionFileError(f"{args.out}: cannot create output folder ({e.strerror})") from None
        for i in chosen:
            src = None
            if source is not None:
                src = source_clip(source, motion.ids[i])
                if src is None:
                    print(f"note: {args.source} has no clip '{motion.ids[i]}' (nor its prefix before '#'); "
                          "drawn without a source", file=sys.stderr)
            stem = os.path.join(args.out, f"{i:04d}_{render_motion.safe_name(motion.ids[i])}")
            for path in render_clip(motion, i, src, control[i], stem, args.formats, args.crf):
                print(path)
    except motionio.MotionFileError as e:
        motionio.fail(str(e))
    return 0


if __name__ == "__main__":
    sys.exit(main())
