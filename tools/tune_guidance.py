#!/usr/bin/python3
"""Tune reconstruction guidance's one step size on the validation split (issue 14).

For every candidate `guidance.scale` and for the unconstrained prior, runs
`motionctl generate` on the OmniControl protocol one density at a time (1, 2, 5
keyframes, 25 %, 100 %; the joints cycled over the tasks) on the val split, reads the
printed Avg. err, and picks the scale with the lowest mean over densities among the
scales that beat the unconstrained prior at every density. Same seed and tasks for
every arm, so the comparison is paired. Prints a markdown table (docs/choices.md
records the one the shipped value came from) and writes it as CSV to --out.

  tools/tune_guidance.py --scales 1 10 100 1000 --samples 6 --out runs/tune_guidance.csv
"""

import argparse
import csv
import os
import re
import subprocess
import sys
import tempfile

DENSITIES = [("1", "[1]", "[]"), ("2", "[2]", "[]"), ("5", "[5]", "[]"),
             ("25%", "[]", "[0.25]"), ("100%", "[]", "[1.0]")]
AVG_ERR = re.compile(r"avg_err\s+([0-9.eE+-]+|nan|inf)")
RATE = re.compile(r"\(([0-9.]+) s/motion\)")


def parse_args(argv):
    p = argparse.ArgumentParser(description="Sweep guidance.scale on the val split, per OmniControl density.")
    p.add_argument("--motionctl", default="build/motionctl", help="the motionctl binary")
    p.add_argument("--scales", type=float, nargs="+", required=True, help="candidate guidance.scale values")
    p.add_argument("--samples", type=int, default=6, help="val clips per density (joints cycled over them)")
    p.add_argument("--joints", default="[0,10,11,15,20,21]", help="protocol.joints (OmniControl's six)")
    p.add_argument("--prior", default="configs/prior/flow_standard_kin.yaml", help="flow prior training config")
    p.add_argument("--data", default="data/fixture_standard.h5", help="motion file (its val split is used)")
    p.add_argument("--fixture", default="configs/data/standard.yaml", help="fixture config that builds --data")
    p.add_argument("--steps", type=int, default=50, help="sampler steps (the standard profile's 50)")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--extra", nargs="*", default=[], help="further generate overrides (generator.guidance.*)")
    p.add_argument("--common", nargs="*", default=[],
                   help="generate overrides for every arm, the prior's too (e.g. generator.sampler.cfg_interval.end=0.97)")
    p.add_argument("--out", required=True, help="CSV of every (arm, density) error")
    return p.parse_args(argv)


def run_arm(args, generator, overrides, density, tmp):
    label, counts, fractions = density
    out = os.path.join(tmp, "samples.h5")
    cmd = [args.motionctl, "generate", "configs/control/keyframes_smoke.yaml", f"generator={generator}",
           f"generator.prior.config={args.prior}", f"data.path={args.data}", f"data.fixture={args.fixture}",
           "data.split=val", f"data.num_samples={args.samples}", f"protocol.joints={args.joints}",
           f"protocol.keyframe_counts={counts}", f"protocol.fractions={fractions}",
           f"generator.sampler.steps={args.steps}", f"run.seed={args.seed}", "run.threads=1",
           f"output={out}"] + args.common + overrides
    r = subprocess.run(cmd, capture_output=True, text=True)
    text = r.stdout + r.stderr
    if r.returncode != 0:
        # A diverged arm (non-finite motions) is a result of the sweep, not a failure of the tool.
        if "non-finite" in text:
            return float("inf"), float("nan")
        sys.exit(f"tune_guidance: `{' '.join(cmd)}` failed (exit {r.returncode}):\n{text}")
    m = AVG_ERR.search(text)
    if not m:
        sys.exit(f"tune_guidance: no avg_err in the output of `{' '.join(cmd)}`:\n{text}")
    rate = RATE.search(text)
    return float(m.group(1)), float(rate.group(1)) if rate else float("nan")


def main(argv):
    args = parse_args(argv)
    arms = [("prior", "flow_tiny", [])]
    for s in args.scales:
        arms.append((f"scale={s:g}", "guidance_tiny", [f"generator.guidance.scale={s:g}"] + args.extra))
    rows = []
    with tempfile.TemporaryDirectory(prefix="tune_guidance_") as tmp:
        for name, gen, ov in arms:
            for d in DENSITIES:
                err, rate = run_arm(args, gen, ov, d, tmp)
                rows.append({"arm": name, "density": d[0], "avg_err": err, "s_per_motion": rate})
                print(f"{name:>14} density {d[0]:>4}: avg_err {err:.4f} m ({rate:.2f} s/motion)", file=sys.stderr)
    prior = {r["density"]: r["avg_err"] for r in rows if r["arm"] == "prior"}
    best, best_mean = None, float("inf")
    print("| arm | " + " | ".join(d[0] for d in DENSITIES) + " | mean | beats prior everywhere |")
    print("|---" * (len(DENSITIES) + 3) + "|")
    for name, _, _ in arms:
        errs = [next(r["avg_err"] for r in rows if r["arm"] == name and r["density"] == d[0]) for d in DENSITIES]
        mean = sum(errs) / len(errs)
        beats = name != "prior" and all(e < prior[d[0]] for e, d in zip(errs, DENSITIES))
        print(f"| {name} | " + " | ".join(f"{e:.4f}" for e in errs) + f" | {mean:.4f} | "
              + ("-" if name == "prior" else ("yes" if beats else "no")) + " |")
        if beats and mean < best_mean:
            best, best_mean = name, mean
    print(f"chosen: {best} (mean Avg. err {best_mean:.4f} m)" if best else
          "chosen: none (no scale beats the prior at every density)")
    tmp_out = args.out + ".tmp"
    with open(tmp_out, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["arm", "density", "avg_err", "s_per_motion"])
        w.writeheader()
        w.writerows(rows)
    os.replace(tmp_out, args.out)
    return 0 if best else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
