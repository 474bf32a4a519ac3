#!/usr/bin/env python3
"""A numpy reference implementation of motionctl's flow prior, run from its exported weights.

`motionctl export --format weights RUN_DIR --out prior.h5 [--probe]` writes the weights (layout in
docs/formats.md, "Flow prior weights"); this file re-implements the eval-mode network of
src/models/flow_prior.cpp, flow_transformer.cpp and text_encoder.cpp (the caption tokenizer,
the post-norm text transformer, AdaLN-Zero blocks with RMSNorm, q/k norm, RoPE, SwiGLU and key
padding, classifier-free guidance) and the Euler sampler step of src/samplers/flow_sampler.cpp,
in numpy only (float64; the time and RoPE angles in float32 as torch forms them). A prior with the
kinematic head (format version 2, src/models/kinematic_head.cpp) is decoded through the same linear
map from its channels (root steps, root height, root position, root-relative joints) to joints.

    python3 tools/flow_reference.py check prior.h5 [--tolerance 1e-4]
        compare with the C++ output stored by --probe (exit 0 within tolerance, 1 beyond it)
    python3 tools/flow_reference.py sample prior.h5 --caption "a person walks" --length 60 \\
        [--steps 99] [--cfg-scale 2.5] [--seed 0] --out motion.npy
        sample one motion (world metres, [length, J, 3]); numpy's noise, not torch's

As a library:

    ref = FlowReference("prior.h5")
    text = ref.encode_captions(["a person walks"])            # [B, text_width]
    v = ref.velocity(x, t, text, mask, cfg_scale=2.5)          # x [B, T, J, 3] normalised units
    x = ref.euler_step(x, t, t_next, text, mask, cfg_scale=2.5)

Bad input (a missing file or dataset, a wrong shape, non-finite values, a damaged file) raises
FlowWeightsError naming the file and dataset; the command line prints it and exits 2.
"""

import argparse
import math
import os
import sys

try:
    import numpy as np
    import h5py
except ImportError as e:  # wrong interpreter
    print(f"error: {e}; run with Debian's /usr/bin/python3 (numpy, h5py)", file=sys.stderr)
    sys.exit(2)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import motionio  # noqa: E402  (tokenizer and checksum seal shared with the motion-file tools)

FORMAT = "motionctl.flow_weights"
FORMAT_VERSION = 2
PAD, UNK, SOS, EOS = 0, 1, 2, 3
_erf = np.vectorize(math.erf, otypes=[np.float64])


class FlowWeightsError(Exception):
    """Bad or unreadable weights file; the message names the file, the dataset and the fix."""


# ------------------------------------------------------------------ layers (torch semantics)

def linear(x, p, name):
    return x @ p[name + ".weight"].T + p[name + ".bias"]


def silu(x):
    return x / (1.0 + np.exp(-x))


def gelu(x):  # torch's default GELU: exact, with erf
    return 0.5 * x * (1.0 + _erf(x / math.sqrt(2.0)))


def layer_norm(x, p, name, eps):
    mu = x.mean(-1, keepdims=True)
    var = ((x - mu) ** 2).mean(-1, keepdims=True)
    return (x - mu) / np.sqrt(var + eps) * p[name + ".weight"] + p[name + ".bias"]


def rms_norm(x, eps, weight=None):
    y = x / np.sqrt((x * x).mean(-1, keepdims=True) + eps)
    return y if weight is None else y * weight


def softmax_masked(s, key_valid):
    """Softmax over the last axis with invalid keys at -inf; key_valid broadcasts against s."""
    s = np.where(key_valid, s, -np.inf)
    s = s - s.max(-1, keepdims=True)
    e = np.exp(s)
    return e / e.sum(-1, keepdims=True)


def conv1d_same(x, weight, bias):
    """torch Conv1d over time with zero padding k // 2: x [B, T, Cin], weight [Cout, Cin, k] -> [B, T, Cout]."""
    k = weight.shape[2]
    T = x.shape[1]
    xp = np.pad(x, ((0, 0), (k // 2, k // 2), (0, 0)))
    out = np.zeros(x.shape[:2] + (weight.shape[0],))
    for j in range(k):
        out += xp[:, j:j + T] @ weight[:, :, j].T
    return out + bias


def timestep_sinusoid(t, dim, time_scale, max_period=10000.0):
    """timestep_sinusoid(t * time_scale, dim): the argument formed in float32 as torch forms it (at
    t * 1000 a float64 argument would differ from torch's by up to ~6e-5 rad)."""
    half = dim // 2
    ts = np.asarray(t, np.float32) * np.float32(time_scale)
    i = np.arange(half, dtype=np.float32)
    freqs = np.exp(((np.float32(-math.log(max_period)) * i) / np.float32(half)).astype(np.float64)).astype(np.float32)
    args = (ts[:, None] * freqs[None, :]).astype(np.float64)
    emb = np.concatenate([np.cos(args), np.sin(args)], -1)
    if dim % 2:
        emb = np.concatenate([emb, np.zeros_like(emb[:, :1])], -1)
    return emb


def rope(x, positions, base):
    """Rotary embedding over the last axis (pairs i, i + D/2), angles in float32 as torch forms them."""
    D = x.shape[-1]
    half = D // 2
    expo = -np.arange(half, dtype=np.float32) * np.float32(2.0 / D)
    inv_freq = np.power(np.float64(base), expo.astype(np.float64)).astype(np.float32)
    ang = (np.asarray(positions, np.float32)[:, None] * inv_freq[None, :]).astype(np.float64)
    cos, sin = np.cos(ang), np.sin(ang)
    x1, x2 = x[..., :half], x[..., half:]
    return np.concatenate([x1 * cos - x2 * sin, x1 * sin + x2 * cos], -1)


# ------------------------------------------------------------------ the kinematic head's decode

def joints_from_kinematic(ch, valid):
    """Channels [B, T, 5 + 3(J-1)] in metres and valid [B, T] bool (a prefix) to world joints [B, T, J, 3]
    (src/models/kinematic_head.cpp): the horizontal root is the running sum of the steps (counted where a
    frame and its predecessor are valid), shifted by the mean over valid frames of (root position channel -
    running sum); the root height is its channel; the other joints are root-relative."""
    ch = np.asarray(ch, np.float64)
    valid = np.asarray(valid, bool)
    B, T, C = ch.shape
    J = (C - 5) // 3 + 1
    step_valid = valid.copy()
    step_valid[:, 0] = False
    step_valid[:, 1:] &= valid[:, :-1]
    path = np.cumsum(ch[:, :, 0:2] * step_valid[..., None], 1)
    vm = valid[..., None].astype(np.float64)
    n = np.maximum(vm.sum(1, keepdims=True), 1.0)
    offset = ((ch[:, :, 3:5] - path) * vm).sum(1, keepdims=True) / n
    rxz = path + offset
    root = np.stack([rxz[..., 0], ch[:, :, 2], rxz[..., 1]], -1)[:, :, None]  # [B, T, 1, 3]
    rel = ch[:, :, 5:].reshape(B, T, J - 1, 3)
    return np.concatenate([root, root + rel], 2)


# ------------------------------------------------------------------ the prior

class FlowReference:
    """A motionctl flow prior loaded from its exported weights file."""

    def __init__(self, path):
        self.path = path
        if not os.path.isfile(path):
            raise FlowWeightsError(f"{path}: no such file; export one with `motionctl export --format weights RUN_DIR "
                                   f"--out {path}`")
        try:
            motionio.check_h5_seal(path)
        except motionio.MotionFileError as e:
            raise FlowWeightsError(f"{e} (re-export it with `motionctl export --format weights RUN_DIR`)") from None
        try:
            with h5py.File(path, "r") as f:
                self._read(f)
        except OSError as e:
            raise FlowWeightsError(f"{path}: not a readable HDF5 file ({e}); re-export it with `motionctl export "
                                   "--format weights RUN_DIR`") from None

    # -------------------------------------------------------------- reading

    def _fix(self):
        return f"re-export it with `motionctl export --format weights RUN_DIR --out {self.path}`"

    def _attr(self, obj, key, where):
        if key not in obj.attrs:
            raise FlowWeightsError(f"{self.path}: attribute '{key}' of {where} is missing; {self._fix()}")
        v = obj.attrs[key]
        if isinstance(v, bytes):
            v = v.decode("utf-8")
        if isinstance(v, np.generic):
            v = v.item()
        return v

    def _read(self, f):
        fmt = self._attr(f, "format", "/")
        if fmt != FORMAT:
            raise FlowWeightsError(f"{self.path}: format '{fmt}', not a flow prior weights file ({FORMAT}); "
                                   f"{self._fix()}")
        version = int(self._attr(f, "format_version", "/"))
        if version > FORMAT_VERSION:
            raise FlowWeightsError(f"{self.path}: format_version {version} is newer than this loader's "
                                   f"({FORMAT_VERSION}); use tools/flow_reference.py of the motionctl that wrote it")
        if "model" not in f or "weights" not in f:
            missing = "model" if "model" not in f else "weights"
            raise FlowWeightsError(f"{self.path}: group '/{missing}' is missing; {self._fix()}")
        m = f["model"]
        a = {k: self._attr(m, k, "/model") for k in (
            "num_joints", "depth", "width", "heads", "head_dim", "mlp_hidden", "cond_dim", "freq_dim", "time_scale",
            "rope_base", "temporal_kernel", "rms_eps", "prediction", "clean_gap_floor", "vocab_size", "text_width",
            "text_layers", "text_heads", "text_ff", "max_words", "layer_norm_eps", "text_adapter")}
        # Version 2 adds the kinematic head; a version-1 file has none (its head writes J * 3 channels).
        for k in ("kinematic_head", "kinematic_noise"):
            a[k] = int(self._attr(m, k, "/model")) if version >= 2 else 0
        a["out_channels"] = int(self._attr(m, "out_channels", "/model")) if version >= 2 else a["num_joints"] * 3
        kin_channels = 5 + (a["num_joints"] - 1) * 3
        expected = kin_channels if a["kinematic_head"] else a["num_joints"] * 3
        if a["out_channels"] != expected:
            raise FlowWeightsError(f"{self.path}: /model out_channels {a['out_channels']} does not match "
                                   f"kinematic_head {a['kinematic_head']} with {a['num_joints']} joints (expected "
                                   f"{expected}); {self._fix()}")
        if a["kinematic_head"] and a["prediction"] != "clean":
            raise FlowWeightsError(f"{self.path}: /model has kinematic_head 1 with prediction '{a['prediction']}' "
                                   f"(the head states the clean endpoint); {self._fix()}")
        if a["kinematic_noise"] and not a["kinematic_head"]:
            raise FlowWeightsError(f"{self.path}: /model has kinematic_noise 1 without kinematic_head; {self._fix()}")
        self.arch = a
        self.config = str(self._attr(f, "config", "/"))
        self.config_hash = str(self._attr(f, "config_hash", "/"))
        self.fps = float(self._attr(f, "fps", "/"))
        self.t_max = int(self._attr(f, "t_max", "/"))
        if "vocab" not in f:
            raise FlowWeightsError(f"{self.path}: dataset '/vocab' is missing; {self._fix()}")
        self.vocab = [w.decode("utf-8") if isinstance(w, bytes) else str(w) for w in f["vocab"][()]]
        if len(self.vocab) != a["vocab_size"]:
            raise FlowWeightsError(f"{self.path}: dataset '/vocab' has {len(self.vocab)} words, /model says "
                                   f"vocab_size {a['vocab_size']}; {self._fix()}")
        self.word_ids = {w: i for i, w in enumerate(self.vocab)}
        self.joint_names = ([n.decode("utf-8") if isinstance(n, bytes) else str(n)
                             for n in f["skeleton/names"][()]] if "skeleton/names" in f else [])

        J, d, h, kt = a["num_joints"], a["width"], a["mlp_hidden"], a["temporal_kernel"]
        E, ff, Lw = a["text_width"], a["text_ff"], a["max_words"]
        io, out_ch = J * 3, a["out_channels"]
        shapes = {"null_text": (E,), "joint_mean": (3,), "joint_std": (3,),
                  "text.embedding.weight": (a["vocab_size"], E), "text.position.weight": (Lw, E),
                  "text.norm.weight": (E,), "text.norm.bias": (E,), "text.out.weight": (E, E), "text.out.bias": (E,)}
        for i in range(a["text_layers"]):
            q = f"text.encoder.layers.{i}."
            shapes.update({q + "self_attn.in_proj_weight": (3 * E, E), q + "self_attn.in_proj_bias": (3 * E,),
                           q + "self_attn.out_proj.weight": (E, E), q + "self_attn.out_proj.bias": (E,),
                           q + "linear1.weight": (ff, E), q + "linear1.bias": (ff,),
                           q + "linear2.weight": (E, ff), q + "linear2.bias": (E,),
                           q + "norm1.weight": (E,), q + "norm1.bias": (E,),
                           q + "norm2.weight": (E,), q + "norm2.bias": (E,)})
        if a["text_adapter"]:
            shapes.update({"text_adapter.0.weight": (E,), "text_adapter.0.bias": (E,),
                           "text_adapter.1.weight": (E, E), "text_adapter.1.bias": (E,),
                           "text_adapter.3.weight": (E, E), "text_adapter.3.bias": (E,)})
        t = "transformer."
        shapes.update({t + "t_mlp.0.weight": (d, a["freq_dim"]), t + "t_mlp.0.bias": (d,),
                       t + "t_mlp.2.weight": (d, d), t + "t_mlp.2.bias": (d,),
                       t + "cond_proj.weight": (d, a["cond_dim"]), t + "cond_proj.bias": (d,),
                       t + "final_ada.weight": (2 * d, d), t + "final_ada.bias": (2 * d,)})
        if kt == 1:
            shapes.update({t + "embed.weight": (d, io), t + "embed.bias": (d,),
                           t + "head.weight": (out_ch, d), t + "head.bias": (out_ch,)})
        else:
            shapes.update({t + "embed_conv.weight": (d, io, kt), t + "embed_conv.bias": (d,),
                           t + "head_conv.weight": (out_ch, d, kt), t + "head_conv.bias": (out_ch,)})
        if a["kinematic_head"]:
            shapes.update({"kin_mean": (out_ch,), "kin_std": (out_ch,)})
        for i in range(a["depth"]):
            b = f"{t}blocks.{i}."
            shapes.update({b + "ada.weight": (6 * d, d), b + "ada.bias": (6 * d,),
                           b + "attn.qkv.weight": (3 * d, d), b + "attn.qkv.bias": (3 * d,),
                           b + "attn.proj.weight": (d, d), b + "attn.proj.bias": (d,),
                           b + "attn.q_norm.weight": (a["head_dim"],), b + "attn.k_norm.weight": (a["head_dim"],),
                           b + "mlp.w1.weight": (h, d), b + "mlp.w1.bias": (h,),
                           b + "mlp.w3.weight": (h, d), b + "mlp.w3.bias": (h,),
                           b + "mlp.w2.weight": (d, h), b + "mlp.w2.bias": (d,)})
        w = f["weights"]
        self.p = {}
        for name, shape in shapes.items():
            self.p[name] = self._array(w, name, shape, "/weights/")
        for k in ("joint_std", "kin_std"):
            if k in self.p and not (self.p[k] > 0).all():
                raise FlowWeightsError(f"{self.path}: dataset '/weights/{k}' must be positive; {self._fix()}")

    def _array(self, group, name, shape, prefix, dtype=np.float64):
        where = prefix + name
        if name not in group:
            raise FlowWeightsError(f"{self.path}: dataset '{where}' is missing; {self._fix()}")
        ds = group[name]
        if not isinstance(ds, h5py.Dataset):
            raise FlowWeightsError(f"{self.path}: '{where}' is a group, not a dataset; {self._fix()}")
        if shape is not None and tuple(ds.shape) != tuple(shape):
            raise FlowWeightsError(f"{self.path}: dataset '{where}' has shape {tuple(ds.shape)}, expected "
                                   f"{tuple(shape)} (from the /model attributes); {self._fix()}")
        arr = np.asarray(ds[()]).astype(dtype)
        if arr.dtype.kind == "f" and not np.isfinite(arr).all():
            raise FlowWeightsError(f"{self.path}: dataset '{where}' holds non-finite values; {self._fix()}")
        return arr

    # -------------------------------------------------------------- text

    def tokenize(self, captions):
        """Token ids [B, max_words] and lengths [B] as encode_captions (src/models/text_encoder.cpp)."""
        L = self.arch["max_words"]
        ids = np.zeros((len(captions), L), np.int64)
        lengths = np.zeros(len(captions), np.int64)
        for b, c in enumerate(captions):
            words = motionio.caption_words(c)[:L - 2]
            row = [SOS] + [self.word_ids.get(w, UNK) for w in words] + [EOS]
            ids[b, :len(row)] = row
            lengths[b] = max(1, len(row))
        return ids, lengths

    def encode_text(self, ids, lengths):
        """Pooled text vectors [B, text_width] (the condition) of token ids [B, L] with lengths [B]."""
        p, a = self.p, self.arch
        ids = np.asarray(ids, np.int64)
        B, L = ids.shape
        E, H = a["text_width"], a["text_heads"]
        Dh, eps = E // H, a["layer_norm_eps"]
        h = p["text.embedding.weight"][ids] + p["text.position.weight"][:L][None]
        valid = np.arange(L)[None, :] < np.asarray(lengths)[:, None]  # [B, L]
        for i in range(a["text_layers"]):
            q_ = f"text.encoder.layers.{i}."
            qkv = h @ p[q_ + "self_attn.in_proj_weight"].T + p[q_ + "self_attn.in_proj_bias"]
            q, k, v = (z.reshape(B, L, H, Dh).transpose(0, 2, 1, 3) for z in np.split(qkv, 3, -1))
            s = (q * (1.0 / math.sqrt(Dh))) @ k.transpose(0, 1, 3, 2)  # q scaled first, as torch's MHA
            att = softmax_masked(s, valid[:, None, None, :]) @ v
            att = linear(att.transpose(0, 2, 1, 3).reshape(B, L, E), p, q_ + "self_attn.out_proj")
            ret = layer_norm(h + att, p, q_ + "norm1", eps)  # post-norm (LibTorch's encoder layer)
            h = layer_norm(ret + linear(gelu(linear(ret, p, q_ + "linear1")), p, q_ + "linear2"), p, q_ + "norm2", eps)
        m = valid[..., None].astype(np.float64)
        pooled = (h * m).sum(1) / np.maximum(m.sum(1), 1.0)
        out = linear(layer_norm(pooled, p, "text.norm", eps), p, "text.out")
        if a["text_adapter"]:  # LayerNorm -> Linear -> GELU -> Linear (model.text_encoder)
            z = layer_norm(out, p, "text_adapter.0", eps)
            out = linear(gelu(linear(z, p, "text_adapter.1")), p, "text_adapter.3")
        return out

    def encode_captions(self, captions):
        return self.encode_text(*self.tokenize(captions))

    def null_text(self, B):
        return np.broadcast_to(self.p["null_text"], (B, self.arch["text_width"])).copy()

    # -------------------------------------------------------------- network

    def network(self, x, t, cond, mask):
        """The transformer's raw output (velocity, or the clean endpoint for a clean prior): [B, T, J, 3], or
        [B, T, out_channels] z-scored kinematic channels with the kinematic head, for x [B, T, J, 3]
        normalised, t [B], cond [B, text_width], mask [B, T] bool (valid frames)."""
        p, a = self.p, self.arch
        x = np.asarray(x, np.float64)
        B, T, J, _ = x.shape
        d, H, Dh, eps = a["width"], a["heads"], a["head_dim"], a["rms_eps"]
        tr = "transformer."
        t = np.broadcast_to(np.asarray(t, np.float32).reshape(-1), (B,))
        valid = np.asarray(mask, bool)
        te = timestep_sinusoid(t, a["freq_dim"], a["time_scale"])
        c = linear(silu(linear(te, p, tr + "t_mlp.0")), p, tr + "t_mlp.2") + linear(cond, p, tr + "cond_proj")
        flat = x.reshape(B, T, J * 3)
        if a["temporal_kernel"] == 1:
            h = linear(flat, p, tr + "embed")
        else:  # padded frames zeroed so the kernel never reads them
            h = conv1d_same(flat * valid[..., None], p[tr + "embed_conv.weight"], p[tr + "embed_conv.bias"])
        positions = np.arange(T, dtype=np.float32)
        key_valid = valid[:, None, None, :]
        sc = silu(c)
        for i in range(a["depth"]):
            b = f"{tr}blocks.{i}."
            shift_a, scale_a, gate_a, shift_m, scale_m, gate_m = np.split(linear(sc, p, b + "ada"), 6, -1)
            z = rms_norm(h, eps) * (1 + scale_a[:, None]) + shift_a[:, None]
            qkv = linear(z, p, b + "attn.qkv").reshape(B, T, 3, H, Dh).transpose(2, 0, 3, 1, 4)  # [3, B, H, T, Dh]
            q = rope(rms_norm(qkv[0], eps, p[b + "attn.q_norm.weight"]), positions, a["rope_base"])
            k = rope(rms_norm(qkv[1], eps, p[b + "attn.k_norm.weight"]), positions, a["rope_base"])
            s = q @ k.transpose(0, 1, 3, 2) / math.sqrt(Dh)
            att = (softmax_masked(s, key_valid) @ qkv[2]).transpose(0, 2, 1, 3).reshape(B, T, d)
            h = h + gate_a[:, None] * linear(att, p, b + "attn.proj")
            z = rms_norm(h, eps) * (1 + scale_m[:, None]) + shift_m[:, None]
            mlp = linear(silu(linear(z, p, b + "mlp.w1")) * linear(z, p, b + "mlp.w3"), p, b + "mlp.w2")
            h = h + gate_m[:, None] * mlp
        shift, scale = np.split(linear(sc, p, tr + "final_ada"), 2, -1)
        z = rms_norm(h, eps) * (1 + scale[:, None]) + shift[:, None]
        if a["temporal_kernel"] == 1:
            out = linear(z, p, tr + "head")
        else:
            out = conv1d_same(z * valid[..., None], p[tr + "head_conv.weight"], p[tr + "head_conv.bias"])
        return out if a["kinematic_head"] else out.reshape(B, T, J, 3)

    def clean(self, out, mask):
        """A clean prior's output as the clean endpoint x1_hat [B, T, J, 3] in normalised units
        (FlowPriorNetImpl::to_clean): the output itself, or the kinematic head's channels decoded."""
        if not self.arch["kinematic_head"]:
            return out
        ch = out * self.p["kin_std"] + self.p["kin_mean"]
        return self.normalize(joints_from_kinematic(ch, mask))

    def draw_noise(self, rng, mask):
        """The source noise x0 [B, T, J, 3] (FlowPriorNetImpl::draw_noise): N(0, I), or with the kinematic
        noise i.i.d. draws in the head's channels at their std (the root-position channels times
        sqrt(valid frames)) decoded to joints and divided by joint_std. numpy's generator, not torch's."""
        mask = np.asarray(mask, bool)
        B, T = mask.shape
        J = self.arch["num_joints"]
        if not self.arch["kinematic_noise"]:
            return rng.standard_normal((B, T, J, 3))
        C = self.arch["out_channels"]
        scale = np.broadcast_to(self.p["kin_std"], (B, 1, C)).copy()
        scale[:, :, 3:5] *= np.sqrt(np.maximum(mask.sum(1), 1)).reshape(B, 1, 1)
        return joints_from_kinematic(rng.standard_normal((B, T, C)) * scale, mask) / self.p["joint_std"]

    def raw_velocity(self, x, t, text, mask):
        """One network call turned into a velocity (FlowPrior::raw_velocity)."""
        out = self.network(x, t, text, mask)
        if self.arch["prediction"] != "clean":
            return out
        t = np.broadcast_to(np.asarray(t, np.float32).reshape(-1), (out.shape[0],)).astype(np.float64)
        gap = np.maximum(1.0 - t, self.arch["clean_gap_floor"]).reshape(-1, 1, 1, 1)
        return (self.clean(out, mask) - np.asarray(x, np.float64)) / gap

    def velocity(self, x, t, text, mask, cfg_scale):
        """Classifier-free guided velocity v_u + s (v_c - v_u) (FlowPrior::velocity)."""
        B = np.asarray(x).shape[0]
        vc = self.raw_velocity(x, t, text, mask)
        vu = self.raw_velocity(x, t, self.null_text(B), mask)
        return vu + cfg_scale * (vc - vu)

    def euler_step(self, x, t, t_next, text, mask, cfg_scale):
        """x + (t_next - t) v: one step of the sampler (EulerStepper), t a scalar of the time grid."""
        v = self.velocity(x, np.full(np.asarray(x).shape[0], t, np.float32), text, mask, cfg_scale)
        return np.asarray(x, np.float64) + (t_next - t) * v

    def normalize(self, world):
        return (np.asarray(world, np.float64) - self.p["joint_mean"]) / self.p["joint_std"]

    def denormalize(self, x):
        return np.asarray(x, np.float64) * self.p["joint_std"] + self.p["joint_mean"]

    def sample(self, captions, lengths, steps=99, cfg_scale=2.5, seed=0):
        """World joints [N, T, J, 3] (zero past each length): Euler over linspace(0, 1, steps + 1) from numpy
        noise (the C++ sampler draws torch's noise, so samples differ; the map from noise to motion is the same)."""
        N, T, J = len(captions), max(lengths), self.arch["num_joints"]
        if any(n < 1 or n > self.t_max for n in lengths):
            raise FlowWeightsError(f"lengths must be 1..{self.t_max} frames (the prior's t_max), got {list(lengths)}")
        mask = np.arange(T)[None, :] < np.asarray(lengths)[:, None]
        x = self.draw_noise(np.random.default_rng(seed), mask)
        text = self.encode_captions(captions)
        grid = np.linspace(0.0, 1.0, steps + 1)
        for k in range(steps):
            x = self.euler_step(x, grid[k], grid[k + 1], text, mask, cfg_scale)
        return self.denormalize(x) * mask[..., None, None]

    # -------------------------------------------------------------- the probe

    def check_probe(self):
        """Largest absolute differences between this implementation and the C++ output of the file's
        /probe group: {name: value}; token ids must match exactly."""
        with h5py.File(self.path, "r") as f:
            if "probe" not in f:
                raise FlowWeightsError(f"{self.path}: has no '/probe' group; export it with `motionctl export "
                                       f"--format weights RUN_DIR --out {self.path} --probe`")
            g = f["probe"]
            r = {k: self._array(g, k, None, "/probe/", np.int64 if k in ("text_ids", "text_lengths") else np.float64)
                 for k in ("text_ids", "text_lengths", "x", "t", "mask", "text", "null_text", "v_cond", "v_uncond",
                           "v_cfg", "x_next")}
            captions = [c.decode("utf-8") if isinstance(c, bytes) else str(c) for c in g["captions"][()]] \
                if "captions" in g else None
            if captions is None:
                raise FlowWeightsError(f"{self.path}: dataset '/probe/captions' is missing; {self._fix()}")
            t, t_next, s = (float(self._attr(g, k, "/probe")) for k in ("t", "t_next", "cfg_scale"))
        x, mask = r["x"], r["mask"].astype(bool)
        ids, lengths = self.tokenize(captions)
        if not (np.array_equal(ids, r["text_ids"]) and np.array_equal(lengths, r["text_lengths"])):
            raise FlowWeightsError(f"{self.path}: the captions {captions} tokenize to other ids here than in "
                                   "'/probe/text_ids' (tokenizer or vocabulary mismatch)")
        text = self.encode_text(ids, lengths)
        null = self.null_text(len(captions))
        out = {"text": text, "null_text": null,
               "v_cond": self.raw_velocity(x, r["t"], text, mask),
               "v_uncond": self.raw_velocity(x, r["t"], null, mask)}
        out["v_cfg"] = out["v_uncond"] + s * (out["v_cond"] - out["v_uncond"])
        out["x_next"] = x + (t_next - t) * out["v_cfg"]
        return {k: float(np.abs(v - r[k]).max()) for k, v in out.items()}


# ------------------------------------------------------------------ command line

def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("check", help="compare with the C++ output stored in /probe")
    c.add_argument("weights")
    c.add_argument("--tolerance", type=float, default=1e-4)
    s = sub.add_parser("sample", help="sample one motion to a .npy file (world metres, [length, J, 3])")
    s.add_argument("weights")
    s.add_argument("--caption", required=True)
    s.add_argument("--length", type=int, required=True)
    s.add_argument("--steps", type=int, default=99)
    s.add_argument("--cfg-scale", type=float, default=2.5)
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    try:
        ref = FlowReference(args.weights)
        if args.cmd == "check":
            diffs = ref.check_probe()
            worst = max(diffs.values())
            for k, v in diffs.items():
                print(f"{k:10s} max |numpy - C++| = {v:.3e}")
            ok = worst <= args.tolerance
            print(f"{'OK' if ok else 'MISMATCH'}: largest difference {worst:.3e} "
                  f"({'within' if ok else 'beyond'} tolerance {args.tolerance:g})")
            return 0 if ok else 1
        if args.steps < 1:
            raise FlowWeightsError(f"--steps must be at least 1, got {args.steps}")
        world = ref.sample([args.caption], [args.length], args.steps, args.cfg_scale, args.seed)[0]
        motionio.atomic_output(args.out, lambda tmp: np.save(tmp, world.astype(np.float32)), suffix=".npy")
        print(f"wrote {args.out}: {args.length} frames x {world.shape[1]} joints (world metres)")
        return 0
    except FlowWeightsError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
