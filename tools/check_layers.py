#!/usr/bin/env python3
"""One-way layers: fails when a source file includes a header of a higher layer.

The layers, lowest first; a file may include headers of its own layer and of any
layer before it, never of one after it (README.md, "Layout"):

    core -> data -> control -> protocols -> models -> samplers -> train -> eval
         -> experiments -> bench -> cli

Every `#include "..."` of every .h/.cpp under src/, eval/ and experiments/ is
resolved the way the compiler resolves it (the including file's folder, then src/,
then the repository root); includes of files outside these layers (system and
third-party headers, src/pch/) are not checked. A folder under src/ that is on no
layer is an error too, so a new folder cannot slip past the check.

Usage: check_layers.py [--root REPO]   exit 0 clean, 1 with one line per violation,
2 on bad usage.
"""

import argparse
import os
import re
import sys

LAYERS = ["core", "data", "control", "protocols", "models", "samplers", "train", "eval", "experiments", "bench",
          "cli"]
# Where each layer's files live, relative to the repository root.
FOLDERS = {
    "core": "src/core", "data": "src/data", "control": "src/control", "protocols": "src/protocols",
    "models": "src/models", "samplers": "src/samplers", "train": "src/train", "eval": "eval",
    "experiments": "experiments", "bench": "src/bench", "cli": "src/cli",
}
NOT_A_LAYER = {"src/pch"}  # the precompiled torch header: includes torch only
INCLUDE = re.compile(r'^\s*#\s*include\s*"([^"]+)"')


def layer_of(rel):
    """The layer of a repository-relative path, or None."""
    rel = rel.replace(os.sep, "/")
    for layer, folder in FOLDERS.items():
        if rel == folder or rel.startswith(folder + "/"):
            return layer
    return None


def resolve(root, including_dir, name):
    """Repository-relative path of an included file, or None when it is not in the tree."""
    for base in (including_dir, os.path.join(root, "src"), root):
        path = os.path.normpath(os.path.join(base, name))
        if os.path.isfile(path):
            return os.path.relpath(path, root)
    return None


def check(root):
    """(violations, problems): one line per upward include / per folder on no layer."""
    violations, problems = [], []
    src = os.path.join(root, "src")
    if os.path.isdir(src):
        for entry in sorted(os.listdir(src)):
            rel = f"src/{entry}"
            if os.path.isdir(os.path.join(src, entry)) and rel not in NOT_A_LAYER and layer_of(rel) is None:
                problems.append(f"{rel}/ is on no layer; add it to LAYERS and FOLDERS in tools/check_layers.py "
                                "and to README.md's layout")
    for layer in LAYERS:
        top = os.path.join(root, FOLDERS[layer])
        for dirpath, _, files in os.walk(top):
            for f in sorted(files):
                if not f.endswith((".h", ".cpp")):
                    continue
                path = os.path.join(dirpath, f)
                rel = os.path.relpath(path, root)
                with open(path, encoding="utf-8", errors="replace") as fh:
                    for lineno, line in enumerate(fh, 1):
                        m = INCLUDE.match(line)
                        if not m:
                            continue
                        target = resolve(root, dirpath, m.group(1))
                        if target is None:
                            continue
                        to = layer_of(target)
                        if to is not None and LAYERS.index(to) > LAYERS.index(layer):
                            violations.append(f"{rel}:{lineno}: {layer} includes \"{m.group(1)}\" of the higher "
                                              f"layer {to}")
    return violations, problems


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                    help="repository root (default: this checkout)")
    args = ap.parse_args()
    if not os.path.isdir(os.path.join(args.root, "src")):
        print(f"check_layers: '{args.root}' has no src/ folder; pass --root REPO", file=sys.stderr)
        return 2
    violations, problems = check(args.root)
    for line in problems + violations:
        print(line)
    if violations or problems:
        print(f"check_layers: {len(violations)} upward include(s), {len(problems)} folder(s) on no layer; layers, "
              f"lowest first: {' -> '.join(LAYERS)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
