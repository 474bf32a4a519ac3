"""Read, validate and write motionctl motion files (HDF5, docs/formats.md) from Python.
Shared by the converter, the renderers and the tests; also holds the default HumanML3D skeleton."""

import dataclasses
import math
import os
import re
import sys
import zlib
from typing import Dict, Iterable, List, NoReturn, Optional

import numpy as np
import h5py

FORMAT_NAME = "motionctl.motion"
FORMAT_VERSION = 1
KNOWN_SPLITS = ("train", "val", "test", "sample")
STR_DTYPE = h5py.string_dtype(encoding="utf-8")


class MotionFileError(Exception):
    """Bad or unreadable input; the message names the file/key and how to fix it."""


# --------------------------------------------------------------------------
# The checksum seal (src/core/h5_seal.h, docs/formats.md): HDF5's 512-byte user
# block, which libhdf5 skips, holds the file size and the CRC-32 of every byte
# after it, so a damaged file is refused before libhdf5 (which can crash on
# damaged metadata) reads it.

SEAL_BLOCK = 512
SEAL_MAGIC = b"motionctl-h5-seal 1\n"


def _body_crc(path: str):
    crc, size = 0, 0
    with open(path, "rb") as f:
        f.seek(SEAL_BLOCK)
        while True:
            buf = f.read(1 << 20)
            if not buf:
                break
            crc = zlib.crc32(buf, crc)
        size = f.seek(0, os.SEEK_END)
    return crc & 0xFFFFFFFF, size


def seal_h5_file(path: str) -> None:
    """Write the seal into the user block of a closed file created with userblock_size=512."""
    crc, size = _body_crc(path)
    block = SEAL_MAGIC + f"size {size}\ncrc32 {crc:08x}\n".encode()
    with open(path, "r+b") as f:
        f.write(block.ljust(SEAL_BLOCK, b"\0"))


def check_h5_seal(path: str) -> bool:
    """True when the file has a matching seal, False when it has none; MotionFileError when it does not match."""
    with open(path, "rb") as f:
        head = f.read(SEAL_BLOCK)
    if not head.startswith(SEAL_MAGIC):
        return False
    m = re.match(rb"size (\d+)\ncrc32 ([0-9a-f]{8})\n", head[len(SEAL_MAGIC):])
    if not m:
        raise MotionFileError(f"{path}: damaged: its checksum header cannot be parsed; re-create the file")
    crc, size = _body_crc(path)
    if size != int(m.group(1)):
        raise MotionFileError(f"{path}: damaged or truncated: {size} bytes, written with {int(m.group(1))}; "
                              "re-create the file")
    if crc != int(m.group(2), 16):
        raise MotionFileError(f"{path}: damaged: its CRC-32 {crc:08x} does not match the one written with it "
                              f"({m.group(2).decode()}); re-create the file")
    return True


# --------------------------------------------------------------------------
# Default skeleton: HumanML3D's 22 joints (SMPL order), facts from
# shared/notes/reference-facts.md section 1. Measured on a real clip, the bone
# lengths are constant to 2e-6 m, so they can be checked against data.

HUMANML3D22_NAMES = [
    "pelvis", "l_hip", "r_hip", "spine1", "l_knee", "r_knee", "spine2",
    "l_ankle", "r_ankle", "spine3", "l_foot", "r_foot", "neck", "l_collar",
    "r_collar", "head", "l_shoulder", "r_shoulder", "l_elbow", "r_elbow",
    "l_wrist", "r_wrist",
]
HUMANML3D22_PARENTS = [-1, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 9, 9, 12, 13, 14, 16, 17, 18, 19]
HUMANML3D22_REST_DIRECTIONS = [
    [0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, -1, 0],
    [0, 1, 0], [0, -1, 0], [0, -1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1],
    [0, 1, 0], [1, 0, 0], [-1, 0, 0], [0, 0, 1], [0, -1, 0], [0, -1, 0],
    [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0],
]
HUMANML3D22_BONE_LENGTHS = [
    0.0, 0.10307, 0.10988, 0.13157, 0.39362, 0.39019, 0.14319, 0.43243,
    0.42564, 0.05736, 0.14338, 0.14942, 0.21936, 0.13749, 0.14338, 0.10304,
    0.13161, 0.12298, 0.25684, 0.26309, 0.26601, 0.26988,
]
HUMANML3D22_CHAINS = [
    [0, 2, 5, 8, 11], [0, 1, 4, 7, 10], [0, 3, 6, 9, 12, 15],
    [9, 14, 17, 19, 21], [9, 13, 16, 18, 20],
]
# Key order is kept stable so the YAML text (and hence the file bytes) is deterministic.
HUMANML3D22_ROLES = {
    "toes": [10, 11],
    "left_foot": [7, 10],
    "right_foot": [8, 11],
    "face": [2, 1, 17, 16],
    "lower_body": [0, 1, 2, 4, 5, 7, 8, 10, 11],
    "upper_body": [3, 6, 9, 12, 13, 14, 15, 16, 17, 18, 19, 20, 21],
    "left_hand": [20],
    "right_hand": [21],
}


def _fmt_num(x) -> str:
    # Integers print without a decimal point so directions read as [1, 0, 0].
    x = float(x)
    if x == int(x) and abs(x) < 1e15:
        return str(int(x))
    return repr(x)


def _fmt_list(values) -> str:
    return "[" + ", ".join(_fmt_num(v) for v in values) + "]"


def skeleton_to_yaml(skel: dict) -> str:
    """The skeleton in the configs/skeletons/*.yaml layout (parseable by load_skeleton_yaml)."""
    lines = [f"name: {skel['name']}", "joints:      # one entry per joint, in index order"]
    for j, name in enumerate(skel["names"]):
        length = float(skel["bone_lengths"][j])
        lines.append(
            f"  - {{name: {name}, parent: {int(skel['parents'][j])}, "
            f"direction: {_fmt_list(skel['rest_directions'][j])}, "
            f"length: {length if length == 0.0 else repr(length)}}}"
        )
    chains = skel.get("chains") or []
    lines.append("chains: [" + ", ".join(_fmt_list(c) for c in chains) + "]")
    roles = skel.get("roles") or {}
    lines.append("roles: {" + ", ".join(f"{k}: {_fmt_list(v)}" for k, v in roles.items()) + "}")
    return "\n".join(lines) + "\n"


def make_skeleton(name, names, parents, rest_directions, bone_lengths, chains=None, roles=None,
                  yaml_text=None, source=None) -> dict:
    """A skeleton dict as read_motion returns it; validated, YAML text generated if not given."""
    skel = {
        "name": str(name),
        "names": [str(n) for n in names],
        "parents": np.asarray(parents, dtype=np.int32),
        "rest_directions": np.asarray(rest_directions, dtype=np.float64).reshape(-1, 3),
        "bone_lengths": np.asarray(bone_lengths, dtype=np.float64).reshape(-1),
        "chains": [list(map(int, c)) for c in (chains or [])],
        "roles": {str(k): list(map(int, v)) for k, v in (roles or {}).items()},
    }
    skel["yaml"] = yaml_text if yaml_text is not None else skeleton_to_yaml(skel)
    validate_skeleton(skel, source or "skeleton " + str(name))
    return skel


def humanml3d_skeleton() -> dict:
    """A fresh copy of the built-in HumanML3D 22-joint skeleton."""
    return make_skeleton("humanml3d22", HUMANML3D22_NAMES, HUMANML3D22_PARENTS,
                         HUMANML3D22_REST_DIRECTIONS, HUMANML3D22_BONE_LENGTHS,
                         HUMANML3D22_CHAINS, HUMANML3D22_ROLES)


def validate_skeleton(skel: dict, source: str) -> None:
    names, parents = skel["names"], skel["parents"]
    dirs, lengths = skel["rest_directions"], skel["bone_lengths"]
    j = len(names)
    if j == 0:
        raise MotionFileError(f"{source}: skeleton has no joints")
    if parents.shape != (j,) or dirs.shape != (j, 3) or lengths.shape != (j,):
        raise MotionFileError(
            f"{source}: skeleton arrays disagree: {j} names, parents {parents.shape}, "
            f"rest_directions {dirs.shape}, bone_lengths {lengths.shape} (expected ({j},), ({j}, 3), ({j},))")
    if len(set(names)) != j:
        raise MotionFileError(f"{source}: skeleton joint names are not unique")
    # Parents preceding children is what lets forward kinematics run in one pass.
    for c in range(j):
        p = int(parents[c])
        if c == 0 and p != -1:
            raise MotionFileError(f"{source}: joint 0 ({names[0]}) must be the root (parent -1), got {p}")
        if c > 0 and not 0 <= p < c:
            raise MotionFileError(
                f"{source}: joint {c} ({names[c]}) has parent {p}; parents must precede their children")
    if not (np.all(np.isfinite(dirs)) and np.all(np.isfinite(lengths))):
        raise MotionFileError(f"{source}: skeleton rest_directions/bone_lengths are not finite")
    norms = np.linalg.norm(dirs[1:], axis=1)
    bad = np.nonzero(np.abs(norms - 1.0) > 1e-6)[0]
    if bad.size:
        c = int(bad[0]) + 1
        raise MotionFileError(f"{source}: rest direction of joint {c} ({names[c]}) is not a unit vector")
    if np.any(lengths[1:] < 0):
        raise MotionFileError(f"{source}: negative bone length")
    for chain in skel.get("chains", []):
        if any(not 0 <= i < j for i in chain):
            raise MotionFileError(f"{source}: chain {chain} refers to a joint outside 0..{j - 1}")
    for role, idx in skel.get("roles", {}).items():
        if any(not 0 <= i < j for i in idx):
            raise MotionFileError(f"{source}: role '{role}' refers to a joint outside 0..{j - 1}")


# --------------------------------------------------------------------------
# A tiny parser for the YAML subset the skeleton files use: block mappings,
# block lists, and flow values ([..], {..}, numbers, bare/quoted strings).
# PyYAML is not a dependency of the project.

class _Flow:
    def __init__(self, text, where):
        self.s, self.i, self.where = text, 0, where

    def fail(self, msg):
        raise MotionFileError(f"{self.where}: {msg} at column {self.i + 1} in '{self.s}'")

    def ws(self):
        while self.i < len(self.s) and self.s[self.i] in " \t":
            self.i += 1

    def value(self, stops):
        self.ws()
        if self.i >= len(self.s):
            self.fail("missing value")
        c = self.s[self.i]
        if c == "[":
            self.i += 1
            out = []
            self.ws()
            if self.s[self.i:self.i + 1] == "]":
                self.i += 1
                return out
            while True:
                out.append(self.value(",]"))
                self.ws()
                if self.s[self.i:self.i + 1] == ",":
                    self.i += 1
                elif self.s[self.i:self.i + 1] == "]":
                    self.i += 1
                    return out
                else:
                    self.fail("expected ',' or ']'")
        if c == "{":
            self.i += 1
            out = {}
            self.ws()
            if self.s[self.i:self.i + 1] == "}":
                self.i += 1
                return out
            while True:
                key = self.value(":,}")
                self.ws()
                if self.s[self.i:self.i + 1] != ":":
                    self.fail("expected ':' after key")
                self.i += 1
                out[str(key)] = self.value(",}")
                self.ws()
                if self.s[self.i:self.i + 1] == ",":
                    self.i += 1
                elif self.s[self.i:self.i + 1] == "}":
                    self.i += 1
                    return out
                else:
                    self.fail("expected ',' or '}'")
        if c in "\"'":
            end = self.s.find(c, self.i + 1)
            if end < 0:
                self.fail("unterminated quoted string")
            text = self.s[self.i + 1:end]
            self.i = end + 1
            return text
        start = self.i
        while self.i < len(self.s) and self.s[self.i] not in stops:
            self.i += 1
        return _scalar(self.s[start:self.i].strip())


def _scalar(text):
    if re.fullmatch(r"[-+]?\d+", text):
        return int(text)
    try:
        return float(text)
    except ValueError:
        pass
    if text in ("true", "True"):
        return True
    if text in ("false", "False"):
        return False
    if text in ("null", "~", ""):
        return None
    return text


def _strip_comment(line):
    quote = None
    for i, c in enumerate(line):
        if quote:
            if c == quote:
                quote = None
        elif c in "\"'":
            quote = c
        elif c == "#" and (i == 0 or line[i - 1] in " \t"):
            return line[:i].rstrip()
    return line.rstrip()


def _parse_flow(text, where):
    p = _Flow(text, where)
    v = p.value("")
    p.ws()
    if p.i != len(text):
        p.fail("unexpected text after value")
    return v


def parse_yaml_subset(text: str, where: str = "<yaml>"):
    """Parse block mappings/lists whose leaves are flow values; enough for skeleton files."""
    lines = []
    for n, raw in enumerate(text.splitlines(), 1):
        if "\t" in raw[:len(raw) - len(raw.lstrip())]:
            raise MotionFileError(f"{where}:{n}: tabs are not allowed for indentation")
        line = _strip_comment(raw)
        if line.strip() and line.strip() != "---":
            lines.append((n, len(line) - len(line.lstrip(" ")), line.strip()))
    pos = 0

    def block(indent):
        nonlocal pos
        n, ind, content = lines[pos]
        if content.startswith("- ") or content == "-":
            out = []
            while pos < len(lines) and lines[pos][1] == indent and lines[pos][2].startswith("-"):
                n, _, content = lines[pos]
                item = content[1:].strip()
                if item and item[0] not in "[{\"'" and re.match(r"^[^:]+:(\s|$)", item):
                    # "- key: value" opens a block mapping whose keys align with "key".
                    col = indent + len(content) - len(content[1:].lstrip())
                    lines[pos] = (n, col, item)
                    out.append(block(col))
                    continue
                pos += 1
                if item:
                    out.append(_parse_flow(item, f"{where}:{n}"))
                elif pos < len(lines) and lines[pos][1] > indent:
                    out.append(block(lines[pos][1]))
                else:
                    out.append(None)
            return out
        out = {}
        while pos < len(lines) and lines[pos][1] == indent:
            n, _, content = lines[pos]
            m = re.match(r"^([^:{}\[\],]+?)\s*:(\s+(.*))?$", content)
            if not m:
                raise MotionFileError(f"{where}:{n}: expected 'key: value', got '{content}'")
            key, rest = m.group(1).strip().strip("\"'"), (m.group(3) or "").strip()
            pos += 1
            if rest:
                out[key] = _parse_flow(rest, f"{where}:{n}")
            elif pos < len(lines) and (lines[pos][1] > indent or
                                       (lines[pos][1] == indent and lines[pos][2].startswith("-"))):
                out[key] = block(lines[pos][1])
            else:
                out[key] = None
        return out

    if not lines:
        return {}
    result = block(lines[0][1])
    if pos != len(lines):
        n, _, content = lines[pos]
        raise MotionFileError(f"{where}:{n}: unexpected indentation at '{content}'")
    return result


def skeleton_from_yaml_text(text: str, where: str) -> dict:
    doc = parse_yaml_subset(text, where)
    if not isinstance(doc, dict):
        raise MotionFileError(f"{where}: expected a mapping with keys name, joints, chains, roles")
    joints = doc.get("joints")
    if not isinstance(joints, list) or not joints:
        raise MotionFileError(f"{where}: key 'joints' must be a non-empty list of "
                              "{name, parent, direction, length} entries")
    names, parents, dirs, lengths = [], [], [], []
    for j, e in enumerate(joints):
        if not isinstance(e, dict) or not {"name", "parent", "direction", "length"} <= set(e):
            raise MotionFileError(f"{where}: joints[{j}] must have name, parent, direction and length")
        d = e["direction"]
        if not (isinstance(d, list) and len(d) == 3 and all(isinstance(x, (int, float)) for x in d)):
            raise MotionFileError(f"{where}: joints[{j}].direction must be a list of 3 numbers")
        if not isinstance(e["parent"], int) or not isinstance(e["length"], (int, float)):
            raise MotionFileError(f"{where}: joints[{j}] parent must be an integer and length a number")
        names.append(str(e["name"]))
        parents.append(e["parent"])
        dirs.append([float(x) for x in d])
        lengths.append(float(e["length"]))
    chains = doc.get("chains") or []
    roles = doc.get("roles") or {}
    if not isinstance(chains, list) or not all(isinstance(c, list) for c in chains):
        raise MotionFileError(f"{where}: key 'chains' must be a list of joint-index lists")
    if not isinstance(roles, dict) or not all(isinstance(v, list) for v in roles.values()):
        raise MotionFileError(f"{where}: key 'roles' must map role names to joint-index lists")
    return make_skeleton(doc.get("name") or "unnamed", names, parents, dirs, lengths, chains, roles,
                         yaml_text=text, source=where)


def load_skeleton_yaml(path: str) -> dict:
    """Parse a configs/skeletons/*.yaml file into a skeleton dict (same keys as read_motion's)."""
    try:
        with open(path, "r", encoding="utf-8") as f:
            text = f.read()
    except OSError as e:
        raise MotionFileError(f"{path}: cannot read skeleton file ({e.strerror}); check the path") from None
    return skeleton_from_yaml_text(text, path)


# --------------------------------------------------------------------------
# The motion file.

@dataclasses.dataclass
class Motion:
    joints: np.ndarray                  # float32 [N, T_max, J, 3], zero past each length
    lengths: np.ndarray                 # int32 [N]
    ids: List[str]
    split: List[str]
    captions: List[List[str]]           # one list (>= 1 caption) per clip
    skeleton: dict                      # names, parents, rest_directions, bone_lengths, name, yaml, chains, roles
    fps: float = 20.0
    labels: Optional[List[str]] = None
    provenance: Dict[str, object] = dataclasses.field(default_factory=dict)
    stats: Optional[Dict[str, object]] = None   # joint_mean, joint_std, [feature_mean, feature_std], feature_layout
    vocab: Optional[List[str]] = None
    path: Optional[str] = None

    @property
    def num_clips(self) -> int:
        return int(self.lengths.shape[0])

    @property
    def t_max(self) -> int:
        return int(self.joints.shape[1])

    def clip(self, i: int) -> np.ndarray:
        """Valid frames of clip i, [lengths[i], J, 3]."""
        return self.joints[i, :int(self.lengths[i])]

    def indices_of_split(self, name: str) -> List[int]:
        return [i for i, s in enumerate(self.split) if s == name]


def _read_strings(f, key, path, expected_len=None) -> List[str]:
    if key not in f:
        raise MotionFileError(f"{path}: dataset '{key}' is missing; the file must follow docs/formats.md")
    ds = f[key]
    if not isinstance(ds, h5py.Dataset) or ds.ndim != 1 or h5py.check_string_dtype(ds.dtype) is None:
        raise MotionFileError(f"{path}: dataset '{key}' must be a 1-D string dataset, "
                              f"got shape {getattr(ds, 'shape', None)} dtype {getattr(ds, 'dtype', None)}")
    if expected_len is not None and ds.shape[0] != expected_len:
        raise MotionFileError(f"{path}: dataset '{key}' has {ds.shape[0]} entries, expected {expected_len}")
    return list(ds.asstr()[()]) if ds.shape[0] else []


def _read_array(f, key, path, ndim, shape=None, kind="f"):
    if key not in f or not isinstance(f[key], h5py.Dataset):
        raise MotionFileError(f"{path}: dataset '{key}' is missing; the file must follow docs/formats.md")
    ds = f[key]
    if ds.ndim != ndim or (shape is not None and tuple(ds.shape) != tuple(shape)):
        want = shape if shape is not None else f"{ndim}-D"
        raise MotionFileError(f"{path}: dataset '{key}' has shape {ds.shape}, expected {want}")
    if ds.dtype.kind not in (("f",) if kind == "f" else ("i", "u")):
        raise MotionFileError(f"{path}: dataset '{key}' has dtype {ds.dtype}, expected "
                              f"{'floating point' if kind == 'f' else 'integer'}")
    return ds[()]


def _attr_value(v):
    # Other HDF5 writers may store a scalar as a 1-element array or a
    # fixed-length byte string; read all of them as the plain value.
    if isinstance(v, np.ndarray) and v.size == 1:
        v = v.reshape(-1)[0]
    if isinstance(v, (bytes, np.bytes_)):
        v = bytes(v).decode("utf-8")
    elif isinstance(v, np.integer):
        v = int(v)
    elif isinstance(v, np.floating):
        v = float(v)
    return v


def _attr_str(attrs, key):
    v = _attr_value(attrs.get(key))
    return v if v is None or isinstance(v, str) else str(v)


def _attr_number(attrs, key):
    v = _attr_value(attrs.get(key))
    if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
        return v
    return None


def read_motion(path: str) -> Motion:
    """Read and validate a motion file; raises MotionFileError naming the file and dataset."""
    if not os.path.isfile(path):
        raise MotionFileError(f"{path}: no such file; pass an existing motion file (*.h5)")
    check_h5_seal(path)
    try:
        f = h5py.File(path, "r")
    except OSError:
        raise MotionFileError(f"{path}: not an HDF5 file (or unreadable); expected a motion file "
                              "written by motionctl or tools/humanml3d_to_h5.py") from None
    with f:
        fmt = _attr_str(f.attrs, "format")
        if fmt != FORMAT_NAME:
            raise MotionFileError(f"{path}: attribute 'format' is {fmt!r}, expected '{FORMAT_NAME}'; "
                                  "this HDF5 file is not a motion file")
        version = _attr_number(f.attrs, "format_version")
        if version != FORMAT_VERSION:
            raise MotionFileError(f"{path}: attribute 'format_version' is "
                                  f"{_attr_value(f.attrs.get('format_version'))!r}, this reader "
                                  f"understands version {FORMAT_VERSION}")
        fps = _attr_number(f.attrs, "fps")
        if fps is None or fps <= 0:
            raise MotionFileError(f"{path}: attribute 'fps' is missing or not a positive number")

        skel = _read_skeleton(f, path)
        j = len(skel["names"])

        joints = _read_array(f, "joints", path, 4)
        n, t_max = joints.shape[0], joints.shape[1]
        if joints.shape[2:] != (j, 3):
            raise MotionFileError(f"{path}: dataset 'joints' has shape {joints.shape}, expected "
                                  f"[N, T_max, {j}, 3] ({j} = skeleton joint count)")
        joints = joints.astype(np.float32, copy=False)
        if not np.all(np.isfinite(joints)):
            bad = int(np.nonzero(~np.isfinite(joints).reshape(n, -1).all(axis=1))[0][0])
            raise MotionFileError(f"{path}: dataset 'joints' has non-finite values (first in clip {bad})")
        lengths = _read_array(f, "lengths", path, 1, (n,), kind="i").astype(np.int32)
        bad = np.nonzero((lengths < 1) | (lengths > t_max))[0]
        if bad.size:
            i = int(bad[0])
            raise MotionFileError(f"{path}: dataset 'lengths' entry {i} is {lengths[i]}, "
                                  f"must be in 1..{t_max} (T_max)")

        ids = _read_strings(f, "ids", path, n)
        if len(set(ids)) != n:
            dup = next(x for x in ids if ids.count(x) > 1)
            raise MotionFileError(f"{path}: dataset 'ids' is not unique ('{dup}' repeats)")
        split = _read_strings(f, "split", path, n)
        unknown = sorted(set(split) - set(KNOWN_SPLITS))
        if unknown:
            raise MotionFileError(f"{path}: dataset 'split' has unknown value(s) {unknown}; "
                                  f"allowed: {', '.join(KNOWN_SPLITS)}")
        labels = _read_strings(f, "labels", path, n) if "labels" in f else None

        text = _read_strings(f, "captions/text", path)
        offsets = _read_array(f, "captions/offsets", path, 1, (n + 1,), kind="i").astype(np.int64)
        if offsets[0] != 0 or offsets[-1] != len(text):
            raise MotionFileError(f"{path}: dataset 'captions/offsets' must start at 0 and end at "
                                  f"{len(text)} (the caption count), got {offsets[0]}..{offsets[-1]}")
        if np.any(np.diff(offsets) < 1):
            i = int(np.nonzero(np.diff(offsets) < 1)[0][0])
            raise MotionFileError(f"{path}: clip {i} ('{ids[i]}') has no caption in 'captions/offsets'; "
                                  "every clip needs at least one")
        captions = [text[offsets[i]:offsets[i + 1]] for i in range(n)]

        provenance = {}
        if "provenance" in f:
            for k, v in f["provenance"].attrs.items():
                provenance[k] = _attr_value(v)

        stats = None
        if "stats" in f:
            g = f["stats"]
            stats = {"feature_layout": _attr_str(g.attrs, "feature_layout")}
            for k in ("joint_mean", "joint_std"):
                stats[k] = _read_array(f, "stats/" + k, path, 1, (3,)).astype(np.float32)
            if ("feature_mean" in g) != ("feature_std" in g):
                raise MotionFileError(f"{path}: group 'stats' has only one of feature_mean/feature_std")
            if "feature_mean" in g:
                fm = _read_array(f, "stats/feature_mean", path, 1).astype(np.float32)
                stats["feature_mean"] = fm
                stats["feature_std"] = _read_array(f, "stats/feature_std", path, 1, fm.shape).astype(np.float32)

        vocab = _read_strings(f, "vocab", path) if "vocab" in f else None
        if vocab is not None:
            check_vocab(vocab, path)

    return Motion(joints=joints, lengths=lengths, ids=ids, split=split, captions=captions,
                  skeleton=skel, fps=float(fps), labels=labels, provenance=provenance,
                  stats=stats, vocab=vocab, path=path)


def _read_skeleton(f, path) -> dict:
    if "skeleton" not in f or not isinstance(f["skeleton"], h5py.Group):
        raise MotionFileError(f"{path}: group 'skeleton' is missing; the file must follow docs/formats.md")
    names = _read_strings(f, "skeleton/names", path)
    j = len(names)
    parents = _read_array(f, "skeleton/parents", path, 1, (j,), kind="i")
    dirs = _read_array(f, "skeleton/rest_directions", path, 2, (j, 3))
    lengths = _read_array(f, "skeleton/bone_lengths", path, 1, (j,))
    g = f["skeleton"]
    name = _attr_str(g.attrs, "name") or "unnamed"
    yaml_text = _attr_str(g.attrs, "yaml") or ""
    chains, roles = [], {}
    if yaml_text:
        # Chains and roles live only in the YAML text. This parser knows a YAML
        # subset only, so text it cannot read costs the roles, not the file; a
        # readable text that disagrees with the datasets is a broken file.
        try:
            from_yaml = skeleton_from_yaml_text(yaml_text, f"{path}: skeleton attr 'yaml'")
        except MotionFileError as e:
            print(f"warning: {e}; chains and roles are unavailable", file=sys.stderr)
            from_yaml = None
        if from_yaml is not None:
            chains, roles = from_yaml["chains"], from_yaml["roles"]
        if from_yaml is not None and (from_yaml["names"] != names or
                                      not np.array_equal(from_yaml["parents"], parents)):
            raise MotionFileError(f"{path}: skeleton attr 'yaml' disagrees with skeleton/names or "
                                  "skeleton/parents")
    return make_skeleton(name, names, parents, dirs, lengths, chains, roles, yaml_text=yaml_text,
                         source=f"{path}: skeleton")


# --------------------------------------------------------------------------
# The constraints of generated samples (/control, docs/formats.md): what `motionctl generate`
# gave each sample, targets written out. Read for drawing them (tools/animate.py).

_DEFAULT_FRAMES = {"trajectory": "all", "planar_root": "all", "camera_2d": "all", "relative": "all",
                   "upper_body_edit": "all", "loop": "ends"}


def _item_frames(g, kind, length, where):
    if "frames" in g:
        frames = np.asarray(g["frames"][()]).reshape(-1).astype(np.int64)
    elif _attr_str(g.attrs, "frames") == "all" or ("frames_start" not in g.attrs and
                                                   _DEFAULT_FRAMES.get(kind) == "all"):
        frames = np.arange(length)
    elif "frames_start" in g.attrs:
        start = int(_attr_number(g.attrs, "frames_start"))
        stop = int(_attr_number(g.attrs, "frames_stop")) if "frames_stop" in g.attrs else -1
        step = int(_attr_number(g.attrs, "frames_step")) if "frames_step" in g.attrs else 1
        frames = np.arange(start, length if stop < 0 else stop, max(1, step))
    elif kind == "loop":
        frames = np.array([0, length - 1])
    else:
        raise MotionFileError(f"{where}: no frames (keyframe items need a 'frames' dataset)")
    if len(frames) and (frames.min() < 0 or frames.max() >= length):
        raise MotionFileError(f"{where}: frames outside 0..{length - 1}")
    return frames


def read_control(path: str, motion: "Motion"):
    """Per sample of a `generate` output, its constraint items as dicts: type, name, joints
    (indices), frames (int array), axes (list), values (float array or None), camera (4 floats or
    None). [] for a file without /control (a dataset) and for an unconstrained sample.
    MotionFileError naming the item when the group is malformed."""
    names = {n: i for i, n in enumerate(motion.skeleton["names"])}
    out = [[] for _ in range(motion.num_clips)]
    with h5py.File(path, "r") as f:
        if "control" not in f:
            return out
        for i in range(motion.num_clips):
            key = f"control/sample_{i:06d}"
            if key not in f:
                continue
            groups = sorted((k for k in f[key] if k.startswith("item_")), key=lambda k: int(k[5:]))
            for k in groups:
                g, where = f[key][k], f"{path}: /{key}/{k}"
                kind = _attr_str(g.attrs, "type")
                joints = list(range(len(names)))
                if "joints" in g:
                    raw = g["joints"][()]
                    joints = []
                    for j in np.atleast_1d(raw):
                        if isinstance(j, bytes) or isinstance(j, str):
                            name = j.decode() if isinstance(j, bytes) else j
                            if name not in names:
                                raise MotionFileError(f"{where}: unknown joint '{name}'")
                            joints.append(names[name])
                        else:
                            joints.append(int(j))
                elif kind == "planar_root":
                    joints = [0]
                item = {"type": kind, "name": _attr_str(g.attrs, "name"), "joints": joints,
                        "frames": _item_frames(g, kind, int(motion.lengths[i]), where),
                        "axes": [int(a) for a in g["axes"][()]] if "axes" in g else [0, 1, 2],
                        "values": np.asarray(g["values"][()], dtype=np.float64) if "values" in g else None,
                        "camera": np.asarray(g["camera"][()], dtype=np.float64) if "camera" in g else None}
                if kind == "planar_root":
                    item["axes"] = [0, 2]
                out[i].append(item)
    return out


def _tmp_sibling(path: str, suffix: str = "") -> str:
    d, base = os.path.split(os.path.abspath(path))
    return os.path.join(d, f".{base}.tmp{os.getpid()}{suffix}")


def atomic_output(path: str, write, suffix: str = ""):
    """Call write(tmp_path), then rename over path; on any failure leave no file behind.
    `suffix` keeps an extension on the temp name for writers that infer the format from it."""
    tmp = _tmp_sibling(path, suffix)
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def write_motion(path: str, joints, lengths, ids, split, captions, skeleton: Optional[dict] = None,
                 fps: float = 20.0, labels=None, provenance: Optional[dict] = None,
                 stats: Optional[dict] = None, vocab=None) -> None:
    """Write a motion file atomically in exactly the docs/formats.md layout.

    `joints` is either an array [N, T_max, J, 3] or an iterable of N clips [lengths[i] (or more), J, 3]
    (streamed, so a full dataset never has to sit padded in memory; T_max = max(lengths)).
    `stats` may hold joint_mean, joint_std, feature_mean, feature_std (arrays) and feature_layout (str).
    Raises MotionFileError on inconsistent input, leaving no file behind.
    """
    skel = skeleton if skeleton is not None else humanml3d_skeleton()
    validate_skeleton(skel, f"{path}: skeleton")
    j = len(skel["names"])
    lengths = np.asarray(lengths)
    if lengths.ndim != 1 or lengths.dtype.kind not in "iu":
        raise MotionFileError(f"{path}: lengths must be a 1-D integer array")
    lengths = lengths.astype(np.int32)
    n = lengths.shape[0]
    if n == 0:
        raise MotionFileError(f"{path}: refusing to write a motion file with no clips")
    ids, split = [str(x) for x in ids], [str(x) for x in split]
    captions = [[str(c) for c in cs] for cs in captions]
    for key, seq in (("ids", ids), ("split", split), ("captions", captions)) + (
            (("labels", labels),) if labels is not None else ()):
        if len(seq) != n:
            raise MotionFileError(f"{path}: '{key}' has {len(seq)} entries, expected {n} (one per clip)")
    if len(set(ids)) != n:
        dup = next(x for x in ids if ids.count(x) > 1)
        raise MotionFileError(f"{path}: ids are not unique ('{dup}' repeats)")
    bad_split = sorted(set(split) - set(KNOWN_SPLITS))
    if bad_split:
        raise MotionFileError(f"{path}: unknown split value(s) {bad_split}; allowed: {', '.join(KNOWN_SPLITS)}")
    empty = [i for i, cs in enumerate(captions) if not cs]
    if empty:
        raise MotionFileError(f"{path}: clip {empty[0]} ('{ids[empty[0]]}') has no caption")
    if lengths.min() < 1:
        raise MotionFileError(f"{path}: lengths must be >= 1")
    if vocab is not None:
        vocab = [str(w) for w in vocab]
        check_vocab(vocab, path)

    if isinstance(joints, np.ndarray):
        if joints.ndim != 4 or joints.shape[0] != n or joints.shape[2:] != (j, 3):
            raise MotionFileError(f"{path}: joints has shape {joints.shape}, expected [{n}, T_max, {j}, 3]")
        t_max = joints.shape[1]
        clips: Iterable = (joints[i] for i in range(n))
    else:
        t_max = int(lengths.max())
        clips = joints
    if lengths.max() > t_max:
        raise MotionFileError(f"{path}: a length exceeds T_max = {t_max}")

    offsets = np.zeros(n + 1, dtype=np.int64)
    offsets[1:] = np.cumsum([len(cs) for cs in captions])
    flat_captions = [c for cs in captions for c in cs]

    def write(tmp):
        _write_body(tmp)
        seal_h5_file(tmp)

    def _write_body(tmp):
        with h5py.File(tmp, "w", userblock_size=SEAL_BLOCK) as f:
            f.attrs["format"] = FORMAT_NAME
            f.attrs["format_version"] = np.int64(FORMAT_VERSION)
            f.attrs["fps"] = np.float64(fps)
            ds = f.create_dataset("joints", shape=(n, t_max, j, 3), dtype=np.float32,
                                  chunks=(1, t_max, j, 3), compression="gzip", compression_opts=4)
            count = 0
            for i, clip in enumerate(clips):
                if i >= n:
                    raise MotionFileError(f"{path}: more joint clips than lengths ({n})")
                clip = np.asarray(clip, dtype=np.float32)
                L = int(lengths[i])
                if clip.ndim != 3 or clip.shape[1:] != (j, 3) or clip.shape[0] < L:
                    raise MotionFileError(f"{path}: clip {i} ('{ids[i]}') has shape {clip.shape}, "
                                          f"expected at least [{L}, {j}, 3]")
                valid = clip[:L]
                if not np.all(np.isfinite(valid)):
                    raise MotionFileError(f"{path}: clip {i} ('{ids[i]}') has non-finite joint positions")
                padded = np.zeros((t_max, j, 3), dtype=np.float32)
                padded[:L] = valid  # frames past the length are defined to be zero
                ds[i] = padded
                count += 1
            if count != n:
                raise MotionFileError(f"{path}: got {count} joint clips, expected {n}")
            f.create_dataset("lengths", data=lengths, dtype=np.int32)
            f.create_dataset("ids", data=ids, dtype=STR_DTYPE)
            f.create_dataset("split", data=split, dtype=STR_DTYPE)
            if labels is not None:
                f.create_dataset("labels", data=[str(x) for x in labels], dtype=STR_DTYPE)
            g = f.create_group("captions")
            g.create_dataset("text", data=flat_captions, dtype=STR_DTYPE)
            g.create_dataset("offsets", data=offsets, dtype=np.int64)

            s = f.create_group("skeleton")
            s.create_dataset("names", data=list(skel["names"]), dtype=STR_DTYPE)
            s.create_dataset("parents", data=np.asarray(skel["parents"], dtype=np.int32))
            s.create_dataset("rest_directions", data=np.asarray(skel["rest_directions"], dtype=np.float64))
            s.create_dataset("bone_lengths", data=np.asarray(skel["bone_lengths"], dtype=np.float64))
            s.attrs["name"] = str(skel["name"])
            s.attrs["yaml"] = skel.get("yaml") or skeleton_to_yaml(skel)

            p = f.create_group("provenance")
            prov = dict(provenance or {})
            for key in ("generator", "version", "seed", "config", "created"):
                prov.setdefault(key, 0 if key == "seed" else "")
            for key, v in prov.items():
                p.attrs[key] = np.int64(v) if key == "seed" else str(v)

            if stats is not None:
                st = f.create_group("stats")
                st.attrs["feature_layout"] = str(stats.get("feature_layout") or "none")
                for key in ("joint_mean", "joint_std"):
                    arr = np.asarray(stats[key], dtype=np.float32)
                    if arr.shape != (3,):
                        raise MotionFileError(f"{path}: stats '{key}' has shape {arr.shape}, expected (3,)")
                    st.create_dataset(key, data=arr)
                if stats.get("feature_mean") is not None:
                    fm = np.asarray(stats["feature_mean"], dtype=np.float32).reshape(-1)
                    fs = np.asarray(stats["feature_std"], dtype=np.float32).reshape(-1)
                    if fm.shape != fs.shape:
                        raise MotionFileError(f"{path}: stats feature_mean/feature_std shapes differ")
                    st.create_dataset("feature_mean", data=fm)
                    st.create_dataset("feature_std", data=fs)
            if vocab is not None:
                f.create_dataset("vocab", data=[str(w) for w in vocab], dtype=STR_DTYPE)

    try:
        atomic_output(path, write)
    except OSError as e:
        raise MotionFileError(f"{path}: cannot write ({e.strerror or e}); check that the folder exists "
                              "and is writable") from None


# The vocabulary format both sides read and write (src/data/text_vocab.h, docs/formats.md
# "Vocabulary"): these four tokens at ids 0-3, then the words of the train captions by
# frequency, ties in byte order.
VOCAB_SPECIALS = ("<pad>", "<unk>", "<sos>", "<eos>")


def caption_words(text: str) -> List[str]:
    """Words of a caption exactly as the C++ tokenizer (src/data/text_vocab.cpp) splits them:
    ASCII letters are lowercased, any byte of a non-ASCII UTF-8 character counts as a letter,
    every other byte (digits, spaces, punctuation) separates words."""
    words, current = [], bytearray()
    for b in text.encode("utf-8"):
        if 65 <= b <= 90:
            current.append(b + 32)
        elif 97 <= b <= 122 or b >= 0x80:
            current.append(b)
        elif current:
            words.append(current.decode("utf-8", "replace"))
            current = bytearray()
    if current:
        words.append(current.decode("utf-8", "replace"))
    return words


def build_vocab(captions: Iterable[str], min_count: int = 1) -> List[str]:
    """The vocabulary of these captions in the one format: VOCAB_SPECIALS, then words with at
    least `min_count` occurrences, most frequent first, ties in byte order (TextVocab::build)."""
    counts: Dict[str, int] = {}
    for c in captions:
        for w in caption_words(c):
            counts[w] = counts.get(w, 0) + 1
    kept = sorted((w for w, n in counts.items() if n >= min_count),
                  key=lambda w: (-counts[w], w.encode("utf-8")))
    return list(VOCAB_SPECIALS) + kept


STD_FLOOR = 1e-4  # NormOptions::std_floor (src/data/normalizer.h): a constant axis normalises to 0


class JointMoments:
    """Per-axis mean and population std over every frame and joint of the clips added, as
    compute_norm_stats (src/data/normalizer.cpp) computes joint_mean/joint_std: float64, std
    floored at STD_FLOOR. Clips are merged with Chan's pairwise update (each clip's own mean
    and squared deviations), which is as accurate as the C++ two passes without a second
    read of the data."""

    def __init__(self):
        self.count, self.mean, self.m2 = 0, np.zeros(3), np.zeros(3)

    def add(self, clip) -> None:
        x = np.asarray(clip, dtype=np.float64).reshape(-1, 3)
        if not len(x):
            return
        n, mean = len(x), x.mean(axis=0)
        m2 = ((x - mean) ** 2).sum(axis=0)
        total = self.count + n
        delta = mean - self.mean
        self.mean = self.mean + delta * (n / total)
        self.m2 = self.m2 + m2 + delta * delta * (self.count * n / total)
        self.count = total

    def stats(self) -> dict:
        std = np.maximum(np.sqrt(self.m2 / self.count), STD_FLOOR)
        return {"joint_mean": self.mean.astype(np.float32), "joint_std": std.astype(np.float32)}


def check_vocab(vocab, where: str) -> None:
    """MotionFileError unless `vocab` is in the one format (specials first, unique words)."""
    if list(vocab[:len(VOCAB_SPECIALS)]) != list(VOCAB_SPECIALS):
        raise MotionFileError(f"{where}: 'vocab' must start with {', '.join(VOCAB_SPECIALS)} (ids 0-3), then the "
                              f"words (docs/formats.md, Vocabulary); got {list(vocab[:4])}. Build it with "
                              "motionio.build_vocab(captions) or re-run tools/humanml3d_to_h5.py")
    seen = set()
    for w in vocab:
        if w in seen:
            raise MotionFileError(f"{where}: 'vocab' lists '{w}' twice; vocabulary words must be unique")
        seen.add(w)


def fail(message: str) -> NoReturn:
    """Exit code 2 with a message on stderr: the tools' contract for bad input."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


if __name__ == "__main__":
    # `python3 tools/motionio.py reseal FILE...`: after editing a sealed file in place
    # on purpose (h5py "a" mode), write its seal anew so motionctl reads it again.
    if len(sys.argv) < 3 or sys.argv[1] != "reseal":
        fail("usage: python3 tools/motionio.py reseal FILE.h5 [...]")
    for p in sys.argv[2:]:
        with open(p, "rb") as fh:
            if not fh.read(SEAL_BLOCK).startswith(SEAL_MAGIC[:12]):
                fail(f"{p}: has no seal block (not written by motionctl or motionio); nothing to reseal")
        seal_h5_file(p)
        print(f"resealed {p}")
