#!/usr/bin/env python3
"""Seeded single-byte-flip campaign against a motionctl input file (issue 16).

Why: libhdf5 trusts the metadata it reads; a flipped byte in an object header or
in the global heap can crash the reader instead of returning an error. This
script flips one byte at a time (seeded, reproducible), runs a motionctl command
on the damaged copy and tallies how it ended: exit 0, exit 2 (a refused input),
exit 1 (an internal error), a signal (a crash) or a time-out (a hang). Only the
last three are defects.

By default the flips avoid the bulk payload of HDF5 datasets (a flip there is a
changed number, which the file format cannot detect) and land in the metadata:
object headers, B-trees, heaps. `--anywhere` flips any byte.

  python3 tools/flip_bytes.py --binary build/motionctl --file small.h5 --flips 60 --seed 1 \
      --command 'score {file}'
"""
import argparse
import os
import random
import shutil
import signal
import subprocess
import sys
import tempfile


def payload_ranges(path):
    """Byte ranges holding dataset payload (chunks or contiguous data); [] when h5py is missing."""
    try:
        import h5py
    except ImportError:
        return []
    ranges = []
    with h5py.File(path, "r") as f:
        def visit(_, obj):
            if not isinstance(obj, h5py.Dataset):
                return
            dsid = obj.id
            if obj.chunks is not None:
                for i in range(dsid.get_num_chunks()):
                    info = dsid.get_chunk_info(i)
                    ranges.append((info.byte_offset, info.byte_offset + info.size))
            else:
                off = dsid.get_offset()
                if off is not None:
                    ranges.append((off, off + dsid.get_storage_size()))
        f.visititems(visit)
    return ranges


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--binary", required=True)
    ap.add_argument("--file", required=True, help="the intact input file")
    ap.add_argument("--command", default="score {file}", help="motionctl arguments; {file} is the damaged copy")
    ap.add_argument("--flips", type=int, default=60)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--timeout", type=float, default=60.0)
    ap.add_argument("--anywhere", action="store_true", help="also flip dataset payload bytes")
    ap.add_argument("--verbose", action="store_true")
    a = ap.parse_args()

    data = open(a.file, "rb").read()
    skip = [] if a.anywhere else payload_ranges(a.file)
    positions = [i for i in range(len(data)) if not any(lo <= i < hi for lo, hi in skip)]
    rng = random.Random(a.seed)
    tally = {}
    bad = []
    work = tempfile.mkdtemp(prefix="flip_")
    try:
        ext = os.path.splitext(a.file)[1]
        for k in range(a.flips):
            pos = rng.choice(positions)
            mask = rng.randrange(1, 256)
            damaged = bytearray(data)
            damaged[pos] ^= mask
            target = os.path.join(work, f"flip{ext}")
            with open(target, "wb") as f:
                f.write(damaged)
            cmd = [a.binary] + a.command.format(file=target).split()
            env = dict(os.environ, OMP_NUM_THREADS="1", CI="1")
            try:
                p = subprocess.run(cmd, capture_output=True, text=True, errors="replace", timeout=a.timeout, env=env)
                if p.returncode < 0:
                    outcome = "signal " + signal.Signals(-p.returncode).name
                else:
                    outcome = f"exit {p.returncode}"
                out = (p.stdout + p.stderr).strip().splitlines()
            except subprocess.TimeoutExpired:
                outcome, out = "timeout", []
            tally[outcome] = tally.get(outcome, 0) + 1
            last = out[-1] if out else ""
            if outcome not in ("exit 0", "exit 2"):
                bad.append((k, pos, mask, outcome, last))
            if a.verbose:
                print(f"flip {k}: byte {pos} ^= 0x{mask:02x}: {outcome}: {last[:160]}")
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(f"{a.flips} flips of {a.file} (seed {a.seed}, {len(positions)} candidate bytes of {len(data)}):")
    for k in sorted(tally):
        print(f"  {k}: {tally[k]}")
    for k, pos, mask, outcome, last in bad:
        print(f"  defect: flip {k} byte {pos} ^= 0x{mask:02x}: {outcome}: {last[:200]}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
