#!/usr/bin/python3
"""Where a generator's anchor error comes from: reads finished table rows (their
samples_r*.h5, docs/formats.md) and prints, per row, the anchor error against the
anchor's frame, and, for Root-3D tasks (keyframe anchors on the pelvis) whose last
anchor lies >= --min-travel m from the start, how far and in which direction the
generated pelvis went by that frame compared with the target:

  travel ratio   = |generated displacement| / |target displacement| (xz plane)
  heading error  = angle between the two displacements, degrees

A generator that travels the right distance in a slightly wrong direction has a
ratio near 1 and errors growing with the anchor's frame; one that ignores the
anchors' distance has a ratio far from 1. Used for docs/choices.md ("Where the
generator-only error comes from").

  tools/anchor_drift.py runs/standard_rows/tmd_no_adapter-* runs/standard_rows/anchorkv-*

With --kinks it prints instead how each row meets its anchors: a method that bends the
whole trajectory toward an anchor leaves the motion as smooth at the anchor frames as
elsewhere; one that meets it by moving the anchor frames alone leaves a spike there. Per
row, the mean second difference |x[t-1] - 2 x[t] + x[t+1]| (cm) of the anchored joint and
of the toes at the anchor frames, 1-3 frames from the nearest anchor, and > 10 frames from
it, and the toes' horizontal speed while in contact (height < --contact m in both frames,
cm per frame) near (<= 3 frames) and far (> 10 frames) from the anchors: foot skating
split by where it happens (docs/choices.md, "ProjFlow meets sparse anchors by spikes").

  tools/anchor_drift.py --kinks runs/standard_next_rows/root3d_projflow-* runs/standard_next_rows/root3d_prior-*

Only numpy and h5py (Debian's /usr/bin/python3).
"""

import argparse
import glob
import os
import sys

import h5py
import numpy as np

FRAME_BINS = [0, 20, 40, 80, 120, 160, 10_000]


def fail(message):
    """Bad input: the message on stderr, exit code 2 (the project's convention)."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def row_records(row_dir, min_travel):
    """Per-anchor (frame, error) pairs and per-task (ratio, heading) of one row."""
    files = sorted(glob.glob(os.path.join(row_dir, "samples_r*.h5")))
    if not files:
        fail(f"{row_dir}: no samples_r*.h5 (not a finished table row; run `motionctl reproduce` first)")
    anchors, tasks = [], []
    for path in files:
        with h5py.File(path, "r") as f:
            if "control" not in f or "joints" not in f:
                fail(f"{path}: no 'control' or 'joints' group (a samples file of a table row is expected)")
            joints = f["joints"][:]
            for i in range(joints.shape[0]):
                sample = f["control"].get(f"sample_{i:06d}")
                if sample is None:
                    continue
                for item in sample.values():
                    if item.attrs.get("type") != "keyframe":
                        continue
                    frames, js, values = item["frames"][:], item["joints"][:], item["values"][:]
                    for a, t in enumerate(frames):
                        for b, j in enumerate(js):
                            anchors.append((t, float(np.linalg.norm(joints[i, t, j] - values[a, b]))))
                    if list(js) != [0]:
                        continue
                    last = int(np.argmax(frames))
                    start = joints[i, 0, 0, [0, 2]]
                    gen = joints[i, frames[last], 0, [0, 2]] - start
                    tgt = values[last, 0, [0, 2]] - start
                    if np.linalg.norm(tgt) < min_travel:
                        continue
                    cos = np.dot(gen, tgt) / (np.linalg.norm(gen) * np.linalg.norm(tgt) + 1e-12)
                    tasks.append((np.linalg.norm(gen) / np.linalg.norm(tgt), np.degrees(np.arccos(np.clip(cos, -1, 1)))))
    return np.array(anchors).reshape(-1, 2), np.array(tasks).reshape(-1, 2)


TOES = (10, 11)  # humanml3d22's `toes` role, as the foot-skating metric reads them


def second_difference(x):
    """|x[t-1] - 2 x[t] + x[t+1]| per interior frame t = 1..T-2 of a (T, 3) track."""
    return np.linalg.norm(x[:-2] - 2 * x[1:-1] + x[2:], axis=1)


def kink_records(row_dir, contact):
    """Per row: lists of second differences (anchored joint, toes) and contact speeds (toes), keyed
    by (quantity, where) with where in 'at' (anchor frames), '1-3', 'far' (> 10 frames)."""
    files = sorted(glob.glob(os.path.join(row_dir, "samples_r*.h5")))
    if not files:
        fail(f"{row_dir}: no samples_r*.h5 (not a finished table row; run `motionctl reproduce` first)")
    out = {}
    add = lambda key, values: out.setdefault(key, []).extend(values.tolist())  # noqa: E731
    for path in files:
        with h5py.File(path, "r") as f:
            if "control" not in f or "joints" not in f or "lengths" not in f:
                fail(f"{path}: no 'control', 'joints' or 'lengths' (a samples file of a table row is expected)")
            joints, lengths = f["joints"][:], f["lengths"][:]
            for i in range(joints.shape[0]):
                sample = f["control"].get(f"sample_{i:06d}")
                if sample is None:
                    continue
                L = int(lengths[i])
                frames, anchored = [], set()
                for item in sample.values():
                    if item.attrs.get("type") == "keyframe":
                        frames += [int(t) for t in item["frames"][:]]
                        anchored |= {int(j) for j in item["joints"][:]}
                if not frames or L < 3:
                    continue
                frames = np.array(sorted(set(frames)))
                mid = np.arange(1, L - 1)
                dist = np.min(np.abs(mid[:, None] - frames[None, :]), axis=1)
                where = {"at": dist == 0, "1-3": (dist >= 1) & (dist <= 3), "far": dist > 10}
                for name, js in (("anchored", sorted(anchored)), ("toes", TOES)):
                    for j in js:
                        d2 = second_difference(joints[i, :L, j])
                        for w, sel in where.items():
                            add((name, w), d2[sel] * 100)
                # contact speed between frames t and t+1, placed at t + 1/2: near when either end is
                steps = np.arange(L - 1)
                dstep = np.min(np.minimum(np.abs(steps[:, None] - frames[None, :]),
                                          np.abs(steps[:, None] + 1 - frames[None, :])), axis=1)
                for j in TOES:
                    y = joints[i, :L, j, 1]
                    speed = np.linalg.norm(joints[i, 1:L, j][:, [0, 2]] - joints[i, :L - 1, j][:, [0, 2]], axis=1)
                    on = (y[1:] < contact) & (y[:-1] < contact)
                    add(("slide", "near"), speed[on & (dstep <= 3)] * 100)
                    add(("slide", "far"), speed[on & (dstep > 10)] * 100)
    return out


def print_kinks(rows, contact):
    records = [(row, kink_records(row, contact)) for row in rows]  # every input checked first
    cols = [("anchored", "at"), ("anchored", "1-3"), ("anchored", "far"), ("toes", "at"), ("toes", "1-3"),
            ("toes", "far"), ("slide", "near"), ("slide", "far")]
    heads = ["anchored joint kink at anchors (cm)", "anchored, 1-3 frames", "anchored, > 10 frames",
             "toe kink at anchors (cm)", "toes, 1-3 frames", "toes, > 10 frames",
             "toe slide in contact, <= 3 frames (cm/frame)", "toe slide, > 10 frames"]
    print("| row | " + " | ".join(heads) + " |")
    print("|---|" + "---:|" * len(heads))
    for row, rec in records:
        cells = [f"{np.mean(rec[c]):.2f}" if rec.get(c) else "–" for c in cols]
        print(f"| {os.path.basename(os.path.normpath(row))} | " + " | ".join(cells) + " |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("rows", nargs="+", help="finished row directories (runs/<profile>_rows/<row>-<hash>)")
    ap.add_argument("--min-travel", type=float, default=0.5, help="skip Root-3D tasks whose target moves less (m)")
    ap.add_argument("--kinks", action="store_true", help="print how each row meets its anchors (spikes, sliding)")
    ap.add_argument("--contact", type=float, default=0.05, help="--kinks: toe height below which a foot is in "
                    "contact (m; the foot-skating metric's threshold)")
    args = ap.parse_args()
    if args.contact <= 0:
        fail(f"--contact {args.contact}: a contact height must be > 0 m (the foot-skating metric uses 0.05)")
    if args.kinks:
        print_kinks(args.rows, args.contact)
        return
    bins = [f"{lo}-{hi - 1}" if hi < 10_000 else f"{lo}+" for lo, hi in zip(FRAME_BINS, FRAME_BINS[1:])]
    records = [(row, *row_records(row, args.min_travel)) for row in args.rows]  # every input checked first
    print("| row | " + " | ".join(f"error, frames {b} (m)" for b in bins) +
          " | Root-3D tasks | travel ratio (median) | heading error (median, deg) | heading within 30 deg |")
    print("|---|" + "---:|" * (len(bins) + 4))
    for row, anchors, tasks in records:
        cells = []
        for lo, hi in zip(FRAME_BINS, FRAME_BINS[1:]):
            sel = (anchors[:, 0] >= lo) & (anchors[:, 0] < hi)
            cells.append(f"{anchors[sel, 1].mean():.2f}" if sel.any() else "–")
        if len(tasks):
            cells += [str(len(tasks)), f"{np.median(tasks[:, 0]):.2f}", f"{np.median(tasks[:, 1]):.0f}",
                      f"{np.mean(tasks[:, 1] < 30):.2f}"]
        else:
            cells += ["0", "–", "–", "–"]
        name = os.path.basename(os.path.normpath(row))
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
