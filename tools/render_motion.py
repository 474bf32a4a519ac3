#!/usr/bin/python3
"""Render clips of any motion file (docs/formats.md) as stick-figure strips (PNG) and,
optionally, small animated 3D GIFs, to eyeball data, samples and results."""

import argparse
import math
import os
import re
import sys
import textwrap

import numpy as np
import matplotlib

matplotlib.use("Agg")
matplotlib.rcParams["text.parse_math"] = False  # captions and ids may contain "$"
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib import animation  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import motionio  # noqa: E402

LEFT_COLOR, RIGHT_COLOR, CENTER_COLOR = "#1f77b4", "#d62728", "#404040"
GIF_FPS = 10.0
GIF_MAX_FRAMES = 100  # keeps a GIF around a few hundred KB

# Figures people can open (issue 17): every pose panel has one fixed size whatever the clip
# does (a clip that travels 30 m, or a diverged sample, changes the zoom, not the panel), and a
# figure never exceeds MAX_PX pixels on a side (Pillow's decompression-bomb guard refuses large
# ones; viewers scale huge ones until poses vanish). Long strips wrap onto further lines.
DPI = 100
MAX_PX = 4000
PANEL_W_IN, PANEL_H_IN = 1.5, 2.1      # one pose panel, inches (150 x 210 px at DPI)
PANEL_TITLE_IN = 0.2                   # its "t=.. (..s)" line
PANEL_GAP_IN = 0.08
MAX_PANELS_PER_LINE = 12


def parse_args(argv):
    p = argparse.ArgumentParser(description="Render motion clips as stick-figure strips and GIFs.")
    p.add_argument("file", help="motion file (.h5)")
    p.add_argument("--out", required=True, help="output folder (created if missing)")
    sel = p.add_mutually_exclusive_group()
    sel.add_argument("--clips", help="comma-separated clip indices, e.g. 0,3,5")
    sel.add_argument("--ids", help="comma-separated clip ids")
    p.add_argument("--count", type=int, default=4, help="without --clips/--ids: render the first COUNT clips")
    p.add_argument("--frames", type=int, default=8, help="poses per strip, evenly spaced (default 8)")
    p.add_argument("--gif", action="store_true", help="also write an animated 3D GIF per clip")
    args = p.parse_args(argv)
    if args.count < 1 or args.frames < 1:
        p.error("--count and --frames must be >= 1")
    return args


def select_clips(motion, args):
    n = motion.num_clips
    if args.clips:
        try:
            idx = [int(x) for x in args.clips.split(",") if x.strip()]
        except ValueError:
            raise motionio.MotionFileError(f"--clips '{args.clips}': expected comma-separated integers") from None
        bad = [i for i in idx if not 0 <= i < n]
        if bad:
            raise motionio.MotionFileError(f"{motion.path}: clip index {bad[0]} out of range; the file has "
                                           f"{n} clips (0..{n - 1})")
        return idx
    if args.ids:
        lookup = {cid: i for i, cid in enumerate(motion.ids)}
        wanted = [x.strip() for x in args.ids.split(",") if x.strip()]
        missing = [x for x in wanted if x not in lookup]
        if missing:
            raise motionio.MotionFileError(f"{motion.path}: no clip with id '{missing[0]}' "
                                           f"(first ids: {', '.join(motion.ids[:5])})")
        return [lookup[x] for x in wanted]
    return list(range(min(args.count, n)))


def joint_sides(names):
    def side(name):
        low = name.lower()
        if low.startswith("l_") or low.startswith("left"):
            return "left"
        if low.startswith("r_") or low.startswith("right"):
            return "right"
        return "center"
    return [side(n) for n in names]


def bone_colors(skeleton):
    colors = {"left": LEFT_COLOR, "right": RIGHT_COLOR, "center": CENTER_COLOR}
    sides = joint_sides(skeleton["names"])
    return [colors[sides[j]] for j in range(len(sides))]


def safe_name(text):
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "clip"


def view_axis(clip):
    """Horizontal screen direction (unit xz) of the side view.

    Travelling clips are seen across their main direction of travel so the path
    reads left to right; near-stationary ones from the side of HumanML3D's
    initial facing (+Z forward), which shows the body in profile."""
    root = clip[:, 0, [0, 2]].astype(np.float64)
    centered = root - root.mean(axis=0)
    if len(root) > 1 and np.abs(centered).max() > 0.3:
        _, _, vt = np.linalg.svd(centered, full_matrices=False)
        u = vt[0]
        if np.dot(root[-1] - root[0], u) < 0:
            u = -u
        return u
    return np.array([0.0, 1.0])  # (x, z) = +Z


def side_view(clip, u):
    """Screen coordinates of the side view along unit xz direction u: horizontal, height and
    depth toward the viewer, each [T, J]."""
    # Right x up points at the camera for a right-handed view: depth = u x Y.
    w = np.array([-u[1], 0.0, u[0]])
    horiz = clip[:, :, 0] * u[0] + clip[:, :, 2] * u[1]
    depth = clip[:, :, 0] * w[0] + clip[:, :, 2] * w[2]
    return horiz, clip[:, :, 1], depth


def strip_frames(length, frames):
    """Up to `frames` evenly spaced frame indices of a clip of `length` frames."""
    return np.unique(np.round(np.linspace(0, length - 1, min(frames, length))).astype(int))


def strip_extent(clip, u):
    """(half width, y_lo, y_hi) of the panels that keep the whole body of every frame in view."""
    horiz, height, _ = side_view(clip, u)
    half_w = max(0.6, float(np.abs(horiz - horiz[:, :1]).max()) + 0.15)
    y_lo = min(-0.05, float(height.min()) - 0.05)
    y_hi = max(float(height.max()) + 0.1, y_lo + 0.5)
    return half_w, y_lo, y_hi


def fit_extent(extent, aspect=PANEL_W_IN / PANEL_H_IN):
    """`extent` grown to the panel's aspect (width / height) so the body fills a fixed-size
    panel at one scale: the floor stays at the bottom, the root at the centre."""
    half_w, y_lo, y_hi = extent
    height = max(y_hi - y_lo, 2.0 * half_w / aspect)
    return height * aspect / 2.0, y_lo, y_lo + height


def extent_size(extent):
    """Height of a fitted extent: the one number that says how far a panel is zoomed out."""
    return extent[2] - extent[1]


def panel_lines(frames, per_line=MAX_PANELS_PER_LINE):
    """(panels per line, lines) for a strip of `frames` poses: long strips wrap instead of widening."""
    per = max(1, min(frames, per_line))
    return per, int(math.ceil(frames / per))


def check_size(fig, path):
    """Refuse to write a figure above MAX_PX on a side (a layout bug, not bad input)."""
    w, h = fig.get_size_inches() * DPI
    if max(w, h) > MAX_PX + 0.5:
        raise RuntimeError(f"{path}: figure of {w:.0f} x {h:.0f} px exceeds {MAX_PX} px; layout bug")


def draw_pose(ax, horiz, height, depth, parents, colors, lw=2.2, zorder=2, alpha=1.0, subject=True):
    """One pose (arrays [J]) as bones, far bones first so the near side is drawn on top. `subject`
    marks it as what its panel shows (the figures' manifest checks that it is in view)."""
    bones = [c for c in range(len(parents)) if parents[c] >= 0]
    bones.sort(key=lambda c: depth[c] + depth[parents[c]])
    # One collection per pose, drawn in list order so far bones stay underneath: a Line2D
    # per bone (~20k artists over a replay's strips) was the figures' main drawing cost.
    segments = [[(horiz[parents[c]], height[parents[c]]), (horiz[c], height[c])] for c in bones]
    ax.add_collection(LineCollection(segments, colors=[colors[c] for c in bones], linewidths=lw,
                                     capstyle="round", zorder=zorder, alpha=alpha,
                                     gid="subject" if subject else None))


def draw_strip(axes, clip, parents, colors, shown, fps, u, extent, ylabel_axes=None):
    """Side-view poses of frames `shown` of `clip` [T, J, 3], one per axis of `axes`, each
    centred on the root; `extent` = fit_extent(strip_extent(...)) (shared so panels have one
    scale), or "per_panel": each panel zoomed to its own pose, its view height in its title (for
    diverged motion, whose frames differ wildly in size). `ylabel_axes`: the axes that get the
    height label (default the first)."""
    horiz, height, depth = side_view(clip, u)
    labelled = [axes[0]] if ylabel_axes is None else list(ylabel_axes)
    for ax, t in zip(axes, shown):
        if isinstance(extent, str):
            half_w, y_lo, y_hi = fit_extent(strip_extent(clip[t:t + 1], u))
            zoom = f", {y_hi - y_lo:.3g} m"
        else:
            (half_w, y_lo, y_hi), zoom = extent, ""
        center = horiz[t, 0]
        ax.plot(horiz[:, 0], height[:, 0], color="0.6", lw=1.0, alpha=0.5, zorder=1)  # root path
        ax.axhline(0.0, color="0.35", lw=1.0, zorder=1)
        draw_pose(ax, horiz[t], height[t], depth[t], parents, colors)
        ax.scatter(horiz[t], height[t], s=6, c=list(colors), zorder=3)
        ax.set_xlim(center - half_w, center + half_w)
        ax.set_ylim(y_lo, y_hi)
        ax.set_aspect("equal")
        ax.set_xticks([])
        if any(ax is a for a in labelled):
            ax.set_ylabel("height (m)", fontsize=7)
            ax.tick_params(labelsize=6)
        else:
            ax.set_yticks([])
        ax.set_title(f"t={t} ({t / fps:.2f}s){zoom}", fontsize=8)
        for side in ("top", "right"):
            ax.spines[side].set_visible(False)


def strip_axes(fig, left, top, per_line, lines, fig_w, fig_h):
    """A grid of fixed-size pose panels whose top-left corner is (left, top) inches from the
    figure's top-left; returns the axes row by row."""
    axes = []
    for line in range(lines):
        for k in range(per_line):
            x = left + k * (PANEL_W_IN + PANEL_GAP_IN)
            y = top + line * (PANEL_H_IN + PANEL_TITLE_IN + PANEL_GAP_IN) + PANEL_TITLE_IN
            axes.append(fig.add_axes((x / fig_w, 1.0 - (y + PANEL_H_IN) / fig_h, PANEL_W_IN / fig_w,
                                      PANEL_H_IN / fig_h)))
    return axes


def render_strip(motion, i, frames, path):
    clip = motion.clip(i).astype(np.float64)
    length = clip.shape[0]
    colors = bone_colors(motion.skeleton)
    u = view_axis(clip)
    shown = strip_frames(length, frames)
    extent = fit_extent(strip_extent(clip, u))
    per_line, lines = panel_lines(len(shown))
    left, head, foot = 0.45, 0.55, 0.3
    fig_w = left + per_line * (PANEL_W_IN + PANEL_GAP_IN) + 0.1
    fig_h = head + lines * (PANEL_H_IN + PANEL_TITLE_IN + PANEL_GAP_IN) + foot
    fig = plt.figure(figsize=(fig_w, fig_h), dpi=DPI)
    axes = strip_axes(fig, left, head, per_line, lines, fig_w, fig_h)
    for ax in axes[len(shown):]:
        ax.set_visible(False)
    firsts = [axes[k * per_line] for k in range(lines)]
    draw_strip(axes[:len(shown)], clip, motion.skeleton["parents"], colors, shown, motion.fps, u, extent,
               ylabel_axes=firsts)
    caption = motion.captions[i][0]
    title = textwrap.shorten(caption, width=max(30, int(11 * fig_w)))
    fig.suptitle(title, fontsize=10, y=1.0 - 0.12 / fig_h, va="top")
    fig.text(0.01, 0.08 / fig_h, f"{motion.ids[i]} [{motion.split[i]}] {length} frames; "
             "blue = left, red = right", fontsize=7, color="0.3")
    check_size(fig, path)
    motionio.atomic_output(path, lambda tmp: fig.savefig(tmp, format="png", dpi=DPI), suffix=".png")
    plt.close(fig)


def render_gif(motion, i, path):
    clip = motion.clip(i).astype(np.float64)
    length = clip.shape[0]
    parents = motion.skeleton["parents"]
    colors = bone_colors(motion.skeleton)
    step = max(1, int(round(motion.fps / GIF_FPS)))
    step = max(step, int(np.ceil(length / GIF_MAX_FRAMES)))
    shown = np.arange(0, length, step)
    # Matplotlib's vertical axis is its third; plotting (x, -z, y) keeps the
    # world right-handed with Y up, so left and right are not mirrored.
    px, py, pz = clip[..., 0], -clip[..., 2], clip[..., 1]
    # The camera follows the root so the body stays large on a long path; the
    # floor grid is fixed in the world, so its drift shows the travel.
    reach = np.hypot(px - px[:, :1], py - py[:, :1]).max()
    floor = min(0.0, float(pz.min()))
    half = max(1.0, reach + 0.3, (float(pz.max()) - floor + 0.1) / 2)
    spacing = 0.5
    n_grid = int(np.ceil(2 * half / spacing)) + 2

    fig = plt.figure(figsize=(4, 4), dpi=64)
    ax = fig.add_subplot(projection="3d")
    fig.subplots_adjust(left=-0.05, right=1.02, bottom=0.0, top=0.95)  # 3D axes pad generously
    ax.set_zlim(floor, floor + 2 * half)
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x", fontsize=7)
    ax.set_ylabel("-z", fontsize=7)
    ax.set_zlabel("y", fontsize=7)
    ax.tick_params(labelsize=6)
    grid_x = [ax.plot([], [], [], color="0.8", lw=0.6)[0] for _ in range(n_grid)]
    grid_y = [ax.plot([], [], [], color="0.8", lw=0.6)[0] for _ in range(n_grid)]
    trail = ax.plot([], [], [], color="0.55", lw=0.9, alpha=0.7)[0]  # root path on the floor
    bones = [c for c in range(len(parents)) if parents[c] >= 0]
    lines = {c: ax.plot([], [], [], color=colors[c], lw=2.0)[0] for c in bones}
    ax.set_title(textwrap.shorten(motion.captions[i][0], width=60), fontsize=8)

    def update(t):
        lo_x, hi_x = px[t, 0] - half, px[t, 0] + half
        lo_y, hi_y = py[t, 0] - half, py[t, 0] + half
        ax.set_xlim(lo_x, hi_x)
        ax.set_ylim(lo_y, hi_y)
        # 3D axes do not clip, so everything drawn is kept inside the window.
        first_x = np.ceil(lo_x / spacing) * spacing
        first_y = np.ceil(lo_y / spacing) * spacing
        for k, line in enumerate(grid_x):
            g = first_x + k * spacing
            line.set_data_3d(*(([g, g], [lo_y, hi_y], [floor, floor]) if g <= hi_x else ([], [], [])))
        for k, line in enumerate(grid_y):
            g = first_y + k * spacing
            line.set_data_3d(*(([lo_x, hi_x], [g, g], [floor, floor]) if g <= hi_y else ([], [], [])))
        inside = ((px[:, 0] >= lo_x) & (px[:, 0] <= hi_x) & (py[:, 0] >= lo_y) & (py[:, 0] <= hi_y))
        path_x = np.where(inside, px[:, 0], np.nan)
        path_y = np.where(inside, py[:, 0], np.nan)
        trail.set_data_3d(path_x, path_y, np.full(length, floor))
        for c in bones:
            p = parents[c]
            lines[c].set_data_3d([px[t, p], px[t, c]], [py[t, p], py[t, c]], [pz[t, p], pz[t, c]])
        return list(lines.values())

    anim = animation.FuncAnimation(fig, update, frames=shown, blit=False)
    writer = animation.PillowWriter(fps=motion.fps / step)
    motionio.atomic_output(path, lambda tmp: anim.save(tmp, writer=writer), suffix=".gif")
    plt.close(fig)


def main(argv=None):
    args = parse_args(sys.argv[1:] if argv is None else argv)
    try:
        motion = motionio.read_motion(args.file)
        chosen = select_clips(motion, args)
        try:
            os.makedirs(args.out, exist_ok=True)
        except OSError as e:
            raise motionio.MotionFileError(f"{args.out}: cannot create output folder ({e.strerror})") from None
        for i in chosen:
            stem = os.path.join(args.out, f"{i:04d}_{safe_name(motion.ids[i])}")
            render_strip(motion, i, args.frames, stem + ".png")
            print(stem + ".png")
            if args.gif:
                render_gif(motion, i, stem + ".gif")
                print(stem + ".gif")
    except motionio.MotionFileError as e:
        motionio.fail(str(e))
    return 0


if __name__ == "__main__":
    sys.exit(main())
