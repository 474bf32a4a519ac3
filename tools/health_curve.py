#!/usr/bin/python3
"""Health of a prior against its training time: runs `motionctl health` on every
snapshot of a run (`motionctl train ... --snapshot-every N`) and on its final
weights, then writes health_curve.csv, health_curve.md and health_curve.png.

Each snapshot is checked through a view directory under --out that holds the
run's config and outputs and links its checkpoints/final.pt to the snapshot, so
the health command judges exactly the weights the run held at that step (EMA
included) and the run directory itself is never written. Training time = the
run's wall time at that step (metrics.csv, summed over resumed segments), in
minutes on the machine that trained it; its thread counts are read from log.txt.

  tools/health_curve.py runs/prior/flow_standard-XXXX --samples 256
"""

import argparse
import csv
import glob
import json
import os
import re
import shutil
import subprocess
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

# Metrics with a health target, as (health.json key, label, how the target reads).
TARGETED = [("fid", "FID / GT floor", "ratio"), ("r_precision_top3", "R-precision top-3 / GT", "ratio"),
            ("foot_skating", "foot skating / GT", "ratio"),
            ("acceleration", "mean |acc| / GT", "ratio"), ("bone_length_std_mm", "bone-length std (mm)", "value")]


def parse_args(argv):
    p = argparse.ArgumentParser(description="Curve of prior health against training CPU time.")
    p.add_argument("run", help="a finished training run with checkpoints/snapshot_*.pt")
    p.add_argument("--samples", type=int, default=256, help="N of each health check (default 256)")
    p.add_argument("--split", choices=("test", "val"), default="test",
                   help="reference split of each check (`motionctl health --split`; default test). val keeps "
                        "the test clips out of a choice of training length or sampler setting")
    p.add_argument("--out", default=None, help="folder of the views and curve files "
                                               "(default runs/health_curve/<run name>[_val])")
    p.add_argument("--motionctl", default=os.environ.get("MOTIONCTL", "build/motionctl"))
    p.epilog = "Arguments after -- go to `motionctl health` (e.g. -- --evaluator CFG key=value)."
    a, rest = p.parse_known_args(argv)
    a.health_args = [x for x in rest if x != "--"]
    return a


def fail(msg):
    print(f"health_curve: {msg}", file=sys.stderr)
    sys.exit(2)


def wall_at_steps(run):
    out = {}
    with open(os.path.join(run, "metrics.csv")) as f:
        for row in csv.DictReader(f):
            out[int(row["step"])] = float(row["wall_time"])
    return out


def run_threads(run):
    """Torch thread counts of the run's segments, from log.txt ('N threads' and resumes)."""
    counts = []
    with open(os.path.join(run, "log.txt")) as f:
        for line in f:
            m = re.search(r"(\d+) threads", line)
            if m:
                counts.append(int(m.group(1)))
    return sorted(set(counts)) or [1]


def make_view(run, weights, view, final):
    """A directory the health command reads as a finished run whose final weights are `weights`
    (the run's validation figures, summary.csv, only where they belong: the final weights)."""
    if os.path.isdir(view):
        shutil.rmtree(view)
    os.makedirs(os.path.join(view, "checkpoints"))
    for name in ("config.yaml", "overrides.txt", "seed.txt") + (("summary.csv",) if final else ()):
        src = os.path.join(run, name)
        if os.path.exists(src):
            shutil.copy(src, os.path.join(view, name))
    with open(os.path.join(view, "DONE"), "w"):
        pass
    shutil.copytree(os.path.join(run, "outputs"), os.path.join(view, "outputs"))
    os.symlink(os.path.abspath(weights), os.path.join(view, "checkpoints", "final.pt"))


def main(argv):
    a = parse_args(argv)
    run = a.run.rstrip("/")
    if not os.path.exists(os.path.join(run, "config.yaml")):
        fail(f"'{run}' is not a run directory (no config.yaml)")
    finished = os.path.exists(os.path.join(run, "DONE"))
    snaps = sorted(glob.glob(os.path.join(run, "checkpoints", "snapshot_*.pt")))
    if not snaps:
        fail(f"'{run}' has no checkpoints/snapshot_*.pt; train it with `motionctl train CONFIG --snapshot-every N`")
    # One folder per split: a view is rebuilt (emptied) before each check.
    out = a.out or os.path.join("runs", "health_curve",
                                os.path.basename(run) + ("" if a.split == "test" else "_val"))
    os.makedirs(out, exist_ok=True)
    walls, threads = wall_at_steps(run), run_threads(run)
    final_step = max(walls)
    points = [(int(re.search(r"snapshot_(\d+)\.pt", s).group(1)), s) for s in snaps]
    if finished:  # an unfinished run: the snapshots so far (run again when it is done)
        points.append((final_step, os.path.join(run, "checkpoints", "final.pt")))
    rows = []
    for step, weights in points:
        view = os.path.join(out, f"step_{step:06d}")
        health = os.path.join(view, "health.json" if a.split == "test" else "health_val.json")
        if not os.path.exists(health):
            make_view(run, weights, view, step == final_step)
            cmd = [a.motionctl, "health", view, "--samples", str(a.samples), "--split", a.split] + a.health_args
            print("+", " ".join(cmd), flush=True)
            r = subprocess.run(cmd)
            if r.returncode != 0:
                fail(f"health check of step {step} failed (exit {r.returncode})")
        with open(health) as f:
            h = json.load(f)
        m = {x["key"]: x for x in h["metrics"]}
        row = {"step": step, "train_minutes": walls.get(step, float("nan")) / 60.0,
               "healthy": h["healthy"], "failed": len(h["failed"])}
        for key, _, _ in TARGETED:
            if key in m:
                row[key] = m[key]["value"]
                row[key + "_ratio"] = m[key]["ratio"]
        rows.append(row)
    keys = list(rows[0].keys())
    with open(os.path.join(out, "health_curve.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    with open(os.path.join(out, "health_curve.md"), "w") as f:
        threads_txt = "/".join(str(t) for t in threads)
        f.write(f"# Health against training time: `{run}` (N = {a.samples}, {a.split} split; trained on "
                f"{threads_txt} torch threads)\n\n")
        f.write("| step | train min | " + " | ".join(lbl for _, lbl, _ in TARGETED) + " | targets missed |\n")
        f.write("|---:|---:|" + "---:|" * len(TARGETED) + "---:|\n")
        for r in rows:
            cells = []
            for key, _, kind in TARGETED:
                v = r.get(key + ("_ratio" if kind == "ratio" else ""))
                cells.append("–" if v is None else f"{v:.3g}")
            f.write(f"| {r['step']} | {r['train_minutes']:.1f} | " + " | ".join(cells) + f" | {r['failed']} |\n")
    fig, axes = plt.subplots(1, len(TARGETED), figsize=(4 * len(TARGETED), 3.2))
    targets = {"fid": 2.0, "r_precision_top3": 0.8, "foot_skating": 3.0, "acceleration": 2.0,
               "bone_length_std_mm": 5.0}
    for ax, (key, lbl, kind) in zip(axes, TARGETED):
        xs = [r["train_minutes"] for r in rows if key in r]
        ys = [r[key + ("_ratio" if kind == "ratio" else "")] for r in rows if key in r]
        ax.plot(xs, ys, "o-")
        ax.axhline(targets[key], color="g", ls="--", lw=1, label="target")
        ax.set_xlabel("training wall minutes")
        ax.set_title(lbl, fontsize=9)
        if key != "r_precision_top3":
            ax.set_yscale("log")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(os.path.join(out, "health_curve.png"), dpi=110)
    print(f"wrote {out}/health_curve.{{csv,md,png}}")


if __name__ == "__main__":
    main(sys.argv[1:])
