#!/usr/bin/python3
"""Summarise a motion file (docs/formats.md) as one multi-panel PNG and a stats.json:
lengths per split, captions, words, labels, root speed and travel, joint heights."""

import argparse
import collections
import json
import os
import sys

import numpy as np
import matplotlib

matplotlib.use("Agg")
matplotlib.rcParams["text.parse_math"] = False  # captions and ids may contain "$"
import matplotlib.pyplot as plt  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import motionio  # noqa: E402

SPLIT_COLORS = {"train": "#1f77b4", "val": "#ff7f0e", "test": "#2ca02c", "sample": "#9467bd"}
TOP_WORDS = 30


def parse_args(argv):
    p = argparse.ArgumentParser(description="Plot and summarise the contents of a motion file.")
    p.add_argument("file", help="motion file (.h5)")
    p.add_argument("--out", required=True, help="output folder (created if missing) for "
                                                "dataset_stats.png and stats.json")
    return p.parse_args(argv)


def splits_in_order(motion):
    present = set(motion.split)
    return [s for s in motionio.KNOWN_SPLITS if s in present]


def compute(motion):
    """Every number the figure shows, as plain Python values (also the stats.json content)."""
    n, fps = motion.num_clips, motion.fps
    lengths = motion.lengths.astype(np.int64)
    splits = splits_in_order(motion)
    all_captions = [c for cs in motion.captions for c in cs]
    word_counts = collections.Counter(w for c in all_captions for w in motionio.caption_words(c))
    caption_lengths = [len(motionio.caption_words(c)) for c in all_captions]
    per_clip = np.array([len(cs) for cs in motion.captions])

    if motion.vocab is not None:
        # Words only: the four special tokens (<pad> <unk> <sos> <eos>) are not counted.
        vocab_size, vocab_source = len(motion.vocab) - len(motionio.VOCAB_SPECIALS), "vocab dataset"
    else:
        # Mirror the converter: vocabulary of the train captions when there is a train split.
        source = [i for i in range(n) if motion.split[i] == "train"] or list(range(n))
        words = {w for i in source for c in motion.captions[i] for w in motionio.caption_words(c)}
        vocab_size = len(words)
        vocab_source = "train captions" if motion.split.count("train") else "all captions"

    valid = np.arange(motion.t_max)[None, :] < lengths[:, None]       # [N, T]
    root = motion.joints[:, :, 0, :].astype(np.float64)                # [N, T, 3]
    step = np.linalg.norm(np.diff(root[:, :, [0, 2]], axis=1), axis=-1) * fps  # horizontal m/s
    speeds = step[valid[:, 1:]]
    final = root[np.arange(n), lengths - 1][:, [0, 2]] - root[:, 0, [0, 2]]
    heights = motion.joints[:, :, :, 1][valid]                          # [frames, J]
    names = motion.skeleton["names"]

    def summary(x):
        x = np.asarray(x, dtype=np.float64)
        if x.size == 0:
            return None
        return {"mean": float(x.mean()), "median": float(np.median(x)), "p95": float(np.percentile(x, 95)),
                "min": float(x.min()), "max": float(x.max())}

    stats = {
        "file": os.path.abspath(motion.path),
        "num_clips": n,
        "clips_per_split": {s: motion.split.count(s) for s in splits},
        "t_max": motion.t_max,
        "fps": fps,
        "num_joints": len(names),
        "skeleton": motion.skeleton["name"],
        "length_frames": dict(summary(lengths),
                              per_split_mean={s: float(lengths[[x == s for x in motion.split]].mean())
                                              for s in splits}),
        "mean_length_s": float(lengths.mean() / fps),
        "captions": {"total": len(all_captions), "per_clip_mean": float(per_clip.mean()),
                     "per_clip_min": int(per_clip.min()), "per_clip_max": int(per_clip.max()),
                     "words_per_caption_mean": float(np.mean(caption_lengths)) if caption_lengths else 0.0},
        "vocab_size": vocab_size,
        "vocab_source": vocab_source,
        "top_words": [[w, c] for w, c in word_counts.most_common(TOP_WORDS)],
        "labels": (dict(sorted(collections.Counter(motion.labels).items()))
                   if motion.labels is not None else None),
        "root_speed_mps": summary(speeds),
        "final_root_distance_m": summary(np.linalg.norm(final, axis=1)),
        "joint_height_m": {names[j]: [float(heights[:, j].min()), float(heights[:, j].max())]
                           for j in range(len(names))},
        "norm_stats": ({k: [float(v) for v in motion.stats[k]] for k in ("joint_mean", "joint_std")}
                       if motion.stats else None),
        "provenance": {k: (v if isinstance(v, (int, float, str)) else str(v))
                       for k, v in motion.provenance.items()},
    }
    arrays = {"lengths": lengths, "caption_lengths": caption_lengths, "per_clip": per_clip,
              "speeds": speeds, "final": final, "heights": heights, "splits": splits}
    return stats, arrays


def plot(motion, stats, arrays, path):
    fig, axes = plt.subplots(3, 3, figsize=(16, 13))
    ax = axes.ravel()
    splits = arrays["splits"]
    lengths = arrays["lengths"]

    bins = np.linspace(0, motion.t_max + 1, min(40, motion.t_max + 1) + 1)
    for s in splits:
        ax[0].hist(lengths[[x == s for x in motion.split]], bins=bins, histtype="step", lw=1.5,
                   color=SPLIT_COLORS.get(s), label=f"{s} ({motion.split.count(s)})")
    ax[0].set(title="Clip length per split", xlabel="frames", ylabel="clips")
    ax[0].legend(fontsize=8)

    cl = arrays["caption_lengths"]
    ax[1].hist(cl, bins=np.arange(0, max(cl, default=1) + 2) - 0.5, color="0.4", edgecolor="white")
    ax[1].set(title=f"Caption length ({stats['captions']['total']} captions)", xlabel="words",
              ylabel="captions")

    top = stats["top_words"]
    if top:
        words, counts = zip(*top)
        ax[2].barh(range(len(words)), counts, color="#1f77b4")
        ax[2].set_yticks(range(len(words)))
        ax[2].set_yticklabels(words, fontsize=7)
        ax[2].invert_yaxis()
    ax[2].set(title=f"Top {len(top)} words (vocab {stats['vocab_size']})", xlabel="occurrences")

    if stats["labels"]:
        labels, counts = zip(*sorted(stats["labels"].items(), key=lambda kv: -kv[1]))
        ax[3].barh(range(len(labels)), counts, color="#9467bd")
        ax[3].set_yticks(range(len(labels)))
        ax[3].set_yticklabels(labels, fontsize=7)
        ax[3].invert_yaxis()
        ax[3].set(title="Labels (motion programs)", xlabel="clips")
    else:
        ax[3].text(0.5, 0.5, "no labels in this file", ha="center", va="center", color="0.4")
        ax[3].set(title="Labels", xticks=[], yticks=[])

    sp = arrays["speeds"]
    if sp.size:
        hi = max(float(np.percentile(sp, 99.5)), 1e-3)
        ax[4].hist(np.clip(sp, 0, hi), bins=50, color="#2ca02c")
    ax[4].set(title="Root horizontal speed (valid frames)", xlabel="m/s (clipped at p99.5)", ylabel="frames")

    final = arrays["final"]
    for s in splits:
        sel = np.array([x == s for x in motion.split])
        ax[5].scatter(final[sel, 0], final[sel, 1], s=6, alpha=0.6, color=SPLIT_COLORS.get(s), label=s)
    ax[5].scatter([0], [0], marker="+", color="k", s=60)
    ax[5].set(title="Final root position relative to frame 0", xlabel="x (m)", ylabel="z (m, forward)")
    ax[5].set_aspect("equal", adjustable="datalim")
    ax[5].legend(fontsize=8)

    h = arrays["heights"]
    names = motion.skeleton["names"]
    jx = np.arange(len(names))
    if h.size:
        lo, p5, p95, hi = (np.min(h, 0), np.percentile(h, 5, axis=0), np.percentile(h, 95, axis=0),
                           np.max(h, 0))
        ax[6].vlines(jx, lo, hi, color="0.6", lw=1)
        ax[6].vlines(jx, p5, p95, color="#d62728", lw=5)
    ax[6].axhline(0, color="0.3", lw=0.8)
    ax[6].set_xticks(jx)
    ax[6].set_xticklabels(names, rotation=90, fontsize=7)
    ax[6].set(title="Joint height: min-max (thin), 5-95% (thick)", ylabel="y (m)")

    pc = arrays["per_clip"]
    ax[7].hist(pc, bins=np.arange(0, pc.max() + 2) - 0.5, color="0.4", edgecolor="white")
    ax[7].set(title="Captions per clip", xlabel="captions", ylabel="clips")

    ls = stats["length_frames"]
    rs = stats["root_speed_mps"] or {"mean": float("nan"), "p95": float("nan")}
    lines = [
        f"file: {os.path.basename(motion.path)}",
        f"skeleton: {stats['skeleton']} ({stats['num_joints']} joints), {stats['fps']:g} fps",
        f"clips: {stats['num_clips']}  " + ", ".join(f"{s} {c}" for s, c in stats["clips_per_split"].items()),
        f"length: mean {ls['mean']:.1f} frames ({stats['mean_length_s']:.2f} s), "
        f"min {ls['min']:.0f}, max {ls['max']:.0f}, T_max {stats['t_max']}",
        f"captions: {stats['captions']['total']}, {stats['captions']['per_clip_mean']:.2f} per clip",
        f"vocab: {stats['vocab_size']} words ({stats['vocab_source']})",
        f"root speed: mean {rs['mean']:.2f} m/s, p95 {rs['p95']:.2f} m/s",
        f"generator: {motion.provenance.get('generator', '?')} {motion.provenance.get('version', '')}",
    ]
    ax[8].axis("off")
    ax[8].text(0.0, 1.0, "\n".join(lines), va="top", ha="left", fontsize=9, family="monospace",
               transform=ax[8].transAxes, wrap=True)
    ax[8].set_title("Summary")

    fig.suptitle(f"Dataset statistics: {motion.path}", fontsize=12)
    fig.tight_layout(rect=(0, 0, 1, 0.97))
    motionio.atomic_output(path, lambda tmp: fig.savefig(tmp, format="png", dpi=80), suffix=".png")
    plt.close(fig)


def write_json(path, data):
    def write(tmp):
        with open(tmp, "w", encoding="utf-8") as f:
            json.dump(data, f, indent=2, ensure_ascii=False)
            f.write("\n")
    motionio.atomic_output(path, write)


def main(argv=None):
    args = parse_args(sys.argv[1:] if argv is None else argv)
    try:
        motion = motionio.read_motion(args.file)
        stats, arrays = compute(motion)
        try:
            os.makedirs(args.out, exist_ok=True)
        except OSError as e:
            raise motionio.MotionFileError(f"{args.out}: cannot create output folder ({e.strerror})") from None
        png = os.path.join(args.out, "dataset_stats.png")
        js = os.path.join(args.out, "stats.json")
        plot(motion, stats, arrays, png)
        write_json(js, stats)
        print(png)
        print(js)
    except motionio.MotionFileError as e:
        motionio.fail(str(e))
    return 0


if __name__ == "__main__":
    sys.exit(main())
