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


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("rows", nargs="+", help="finished row directories (runs/<profile>_rows/<row>-<hash>)")
    ap.add_argument("--min-travel", type=float, default=0.5, help="skip Root-3D tasks whose target moves less (m)")
    args = ap.parse_args()
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
