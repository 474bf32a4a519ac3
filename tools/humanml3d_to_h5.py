#!/usr/bin/python3
"""Convert a HumanML3D folder (new_joints/, texts/, train/val/test.txt) into one motionctl
motion file (docs/formats.md), with train-split joint statistics and vocabulary."""

import argparse
import datetime
import math
import os
import shlex
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import motionio  # noqa: E402

VERSION = "1.1"  # 1.1: vocabulary with <pad> <unk> <sos> <eos> by frequency; std floored as in C++
FPS = 20.0  # HumanML3D is resampled to 20 fps; caption spans are in seconds


def parse_args(argv):
    p = argparse.ArgumentParser(
        description="Convert a HumanML3D folder to a motionctl motion file (HDF5).",
        epilog="Example: humanml3d_to_h5.py data/HumanML3D data/humanml3d.h5 --limit 100")
    p.add_argument("root", help="HumanML3D folder holding new_joints/, texts/ and <split>.txt")
    p.add_argument("out", help="output motion file (.h5); written atomically")
    p.add_argument("--max-len", type=int, default=196, help="crop clips to this many frames (default 196)")
    p.add_argument("--min-len", type=int, default=40, help="skip clips shorter than this (default 40)")
    p.add_argument("--splits", default="train,val,test", help="comma-separated split files to read")
    p.add_argument("--no-mirror", action="store_true", help="drop mirrored clips (ids starting with 'M')")
    p.add_argument("--limit", type=int, default=None,
                   help="use only the first N ids of each split file (quick experiments)")
    p.add_argument("--skeleton", default=None,
                   help="skeleton YAML (configs/skeletons/humanml3d22.yaml); default: the built-in "
                        "HumanML3D 22-joint skeleton")
    args = p.parse_args(argv)
    if args.min_len < 1 or args.max_len < args.min_len:
        p.error(f"need 1 <= --min-len <= --max-len, got --min-len {args.min_len} --max-len {args.max_len}")
    if args.limit is not None and args.limit < 1:
        p.error("--limit must be >= 1")
    args.splits = [s.strip() for s in args.splits.split(",") if s.strip()]
    bad = [s for s in args.splits if s not in ("train", "val", "test")]
    if bad or not args.splits:
        p.error(f"--splits takes a comma-separated subset of train,val,test, got {bad or 'nothing'}")
    return args


def parse_caption_line(line):
    """`caption#tokens#from#to` -> (caption, from_s, to_s); (0, 0) means the whole clip."""
    parts = line.rstrip("\n").split("#")
    caption = parts[0].strip()
    start = end = 0.0
    if len(parts) >= 4:
        try:
            start, end = float(parts[2]), float(parts[3])
        except ValueError:
            start = end = 0.0
        # HumanML3D's loaders treat NaN spans as 0.0 (whole clip); do the same.
        start = 0.0 if math.isnan(start) else start
        end = 0.0 if math.isnan(end) else end
    return caption, start, end


def read_captions(path):
    """Captions of one clip grouped by span: {(from, to): [caption, ...]} in file order."""
    spans = {}
    with open(path, "r", encoding="utf-8") as f:
        for line in f:
            caption, start, end = parse_caption_line(line)
            if caption:
                spans.setdefault((start, end), []).append(caption)
    return spans


def load_joints(path, num_joints):
    try:
        data = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as e:
        raise motionio.MotionFileError(f"{path}: cannot read as a .npy array ({e}); "
                                       "re-export the HumanML3D new_joints file") from None
    if data.ndim != 3 or data.shape[1:] != (num_joints, 3) or data.dtype.kind != "f":
        raise motionio.MotionFileError(
            f"{path}: shape {data.shape} dtype {data.dtype}, expected float (T, {num_joints}, 3); "
            "new_joints/ must hold HumanML3D joint positions (not new_joint_vecs features)")
    return data.astype(np.float32, copy=False)


def check_layout(root, splits):
    if not os.path.isdir(root):
        raise motionio.MotionFileError(f"{root}: no such folder; pass the HumanML3D root folder "
                                       "(the one holding new_joints/ and texts/)")
    for sub in ("new_joints", "texts"):
        d = os.path.join(root, sub)
        if not os.path.isdir(d):
            raise motionio.MotionFileError(f"{d}: folder is missing; a HumanML3D root needs new_joints/ "
                                           "(T,22,3) .npy files and texts/ caption files")
    for split in splits:
        f = os.path.join(root, split + ".txt")
        if not os.path.isfile(f):
            raise motionio.MotionFileError(f"{f}: split file is missing; create it or leave '{split}' out "
                                           "of --splits")


def collect_clips(args, skeleton):
    """First pass: decide every output clip (source file, frame range, captions) and the stats."""
    j = len(skeleton["names"])
    clips = []      # dicts: id, source, split, start, end, captions
    seen = {}       # source id -> split file it came from
    report = {"too_short": 0, "cropped": 0, "spans_added": 0, "spans_dropped": 0,
              "mirror_dropped": 0, "no_caption": 0, "non_finite": []}
    train_moments = motionio.JointMoments()
    train_captions = []

    for split in args.splits:
        split_file = os.path.join(args.root, split + ".txt")
        with open(split_file, "r", encoding="utf-8") as f:
            ids = [line.strip() for line in f if line.strip()]
        if args.no_mirror:
            kept = [i for i in ids if not i.startswith("M")]
            report["mirror_dropped"] += len(ids) - len(kept)
            ids = kept
        if args.limit is not None:
            ids = ids[:args.limit]
        for sid in ids:
            if sid in seen:
                raise motionio.MotionFileError(
                    f"{split_file}: id '{sid}' is also listed in {seen[sid]}.txt; a clip may be in one "
                    "split only")
            seen[sid] = split
            npy = os.path.join(args.root, "new_joints", sid + ".npy")
            txt = os.path.join(args.root, "texts", sid + ".txt")
            if not os.path.isfile(npy):
                raise motionio.MotionFileError(f"{npy}: joint file for id '{sid}' (listed in {split_file}) "
                                               "is missing; restore it or remove the id from the split file")
            if not os.path.isfile(txt):
                raise motionio.MotionFileError(f"{txt}: caption file for id '{sid}' (listed in {split_file}) "
                                               "is missing; restore it or remove the id from the split file")
            data = load_joints(npy, j)
            if not np.all(np.isfinite(data)):
                report["non_finite"].append(sid)  # a data defect, not a layout error: skip the clip
                continue
            total = data.shape[0]
            if total < args.min_len:
                report["too_short"] += 1
                continue
            spans = read_captions(txt)
            new = []
            if (0.0, 0.0) in spans:
                new.append({"id": sid, "start": 0, "end": total, "captions": spans.pop((0.0, 0.0))})
            for (t0, t1), caps in spans.items():
                # Same frame arithmetic as the HumanML3D loaders: motion[int(f*20):int(t*20)].
                start, end = int(t0 * FPS), min(int(t1 * FPS), total)
                if end - start < args.min_len:
                    report["spans_dropped"] += 1
                    continue
                report["spans_added"] += 1
                new.append({"id": f"{sid}#{float(t0)!r}_{float(t1)!r}", "start": start, "end": end,
                            "captions": caps})
            if not new:
                report["no_caption"] += 1
                continue
            for c in new:
                if c["end"] - c["start"] > args.max_len:
                    c["end"] = c["start"] + args.max_len
                    report["cropped"] += 1
                c["source"] = npy
                c["split"] = split
                clips.append(c)
                if split == "train":
                    train_moments.add(data[c["start"]:c["end"]])
                    train_captions.extend(c["captions"])

    stats = vocab = None
    if train_moments.count:
        # Joint statistics as the C++ side computes them (population std floored at 1e-4);
        # no feature statistics: motionctl computes those from the train split with its own
        # feature code when a component needs them (docs/formats.md, "Statistics").
        stats = dict(train_moments.stats(), feature_layout="none")
        vocab = motionio.build_vocab(train_captions)
    return clips, stats, vocab, report


def convert(args, argv):
    skeleton = motionio.load_skeleton_yaml(args.skeleton) if args.skeleton else motionio.humanml3d_skeleton()
    check_layout(args.root, args.splits)
    out_dir = os.path.dirname(os.path.abspath(args.out))
    if not os.path.isdir(out_dir):
        raise motionio.MotionFileError(f"{args.out}: output folder {out_dir} does not exist; create it first")

    clips, stats, vocab, report = collect_clips(args, skeleton)
    if not clips:
        raise motionio.MotionFileError(
            f"{args.root}: no clip survived (min-len {args.min_len}, splits {','.join(args.splits)}); "
            "check the split files and --min-len")

    j = len(skeleton["names"])

    def stream():
        # Second pass re-reads each file so the padded dataset never sits in memory.
        for c in clips:
            yield load_joints(c["source"], j)[c["start"]:c["end"]]

    provenance = {
        "generator": "humanml3d_to_h5.py",
        "version": VERSION,
        "seed": 0,
        "config": " ".join(shlex.quote(a) for a in ["humanml3d_to_h5.py"] + list(argv)),
        "created": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }
    motionio.write_motion(
        args.out, stream(), [c["end"] - c["start"] for c in clips], [c["id"] for c in clips],
        [c["split"] for c in clips], [c["captions"] for c in clips], skeleton=skeleton, fps=FPS,
        provenance=provenance, stats=stats, vocab=vocab)

    per_split = {s: sum(1 for c in clips if c["split"] == s) for s in args.splits}
    print(f"wrote {args.out}: {len(clips)} clips ({', '.join(f'{s} {n}' for s, n in per_split.items())}), "
          f"T_max {max(c['end'] - c['start'] for c in clips)}")
    print(f"skipped {report['too_short']} clips shorter than {args.min_len} frames; "
          f"cropped {report['cropped']} to {args.max_len}; sub-span clips: {report['spans_added']} added, "
          f"{report['spans_dropped']} dropped (< {args.min_len} frames)")
    if report["mirror_dropped"]:
        print(f"dropped {report['mirror_dropped']} mirrored ids (--no-mirror)")
    if report["no_caption"]:
        print(f"skipped {report['no_caption']} clips without a usable caption")
    if report["non_finite"]:
        bad = report["non_finite"]
        print(f"skipped {len(bad)} clips with non-finite joints: {', '.join(bad[:5])}{' ...' if len(bad) > 5 else ''}")
    if stats is None:
        print("no train clips selected: the file has no stats group and no vocab")
    else:
        mean = ", ".join(f"{x:.4f}" for x in stats["joint_mean"])
        std = ", ".join(f"{x:.4f}" for x in stats["joint_std"])
        print(f"train joint mean ({mean}) std ({std}); vocab {len(vocab) - len(motionio.VOCAB_SPECIALS)} words "
              f"+ {len(motionio.VOCAB_SPECIALS)} special tokens")


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    args = parse_args(argv)
    try:
        convert(args, argv)
    except motionio.MotionFileError as e:
        motionio.fail(str(e))
    return 0


if __name__ == "__main__":
    sys.exit(main())
