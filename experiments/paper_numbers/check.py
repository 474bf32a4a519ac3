#!/usr/bin/python3
"""Structural check of the paper-number YAML files in this folder (format: README.md).
Usage: /usr/bin/python3 experiments/paper_numbers/check.py   (exit 1 and one line per problem on failure)"""
import glob
import os
import sys

import yaml

KINDS = {"reference", "external", "ours", "ablation", "baseline_ours"}
BETTER = {"lower", "higher", "closer_to_real", None}
REQUIRED = ["paper", "table", "title", "source", "setting", "columns", "rows", "doubts"]


def check(path):
    problems = []
    d = yaml.safe_load(open(path))
    for k in REQUIRED:
        if k not in d:
            problems.append(f"missing top-level key '{k}'")
    if problems:
        return problems
    cols = [c["key"] for c in d["columns"]]
    if len(set(cols)) != len(cols):
        problems.append("duplicate column keys")
    for c in d["columns"]:
        if c.get("better", None) not in BETTER:
            problems.append(f"column {c['key']}: bad 'better' {c.get('better')!r}")
    sections = {s["key"]: s for s in d.get("sections") or []}
    for s in sections.values():
        for k in s.get("columns", []):
            if k not in cols:
                problems.append(f"section {s['key']}: column {k} not in columns")
    for r in d["rows"]:
        m = r.get("method")
        if r.get("kind") not in KINDS:
            problems.append(f"row {m}: bad kind {r.get('kind')!r}")
        has_id = "ours_id" in r
        if r.get("kind") in ("ours", "ablation", "baseline_ours") and not has_id:
            problems.append(f"row {m}: kind {r['kind']} needs ours_id")
        if r.get("kind") in ("reference", "external") and has_id:
            problems.append(f"row {m}: kind {r['kind']} must not have ours_id")
        sec = r.get("section")
        if sec is not None and sec not in sections:
            problems.append(f"row {m}: unknown section {sec!r}")
        allowed = sections[sec].get("columns", cols) if sec in sections else cols
        for k, v in r.get("values", {}).items():
            if k not in allowed:
                problems.append(f"row {m}: value key {k} not a column of its section")
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))):
                problems.append(f"row {m}: {k} = {v!r} is not a number or null")
    return problems


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    files = sorted(glob.glob(os.path.join(here, "*", "table*.yaml")))
    bad = 0
    for f in files:
        for p in check(f):
            print(f"{os.path.relpath(f, here)}: {p}")
            bad += 1
    print(f"{len(files)} files, {bad} problems")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
