#!/usr/bin/env python3
"""Reference reader of flashmat .nmat files (docs/NMAT.md), numpy only.

Renders a neural material under one point light and camera exactly as
`flashmat relight` does, as an executable check of the format description:

    python3 scripts/nmat_render.py material.nmat --light 1,1,3 --view 0,0,4.010781 -o out.npy
    python3 scripts/nmat_render.py material.nmat --light 1,1,3 --compare relit.exr

--compare reads a linear EXR written by `flashmat relight ... -o relit.exr`
(needs the OpenEXR Python module) or a .npy array [3, H, W].
"""
import argparse
import json
import struct
import sys
import zlib

import numpy as np


def read_nmat(path):
    data = open(path, "rb").read()
    (n,) = struct.unpack("<Q", data[:8])
    header = json.loads(data[8 : 8 + n])
    meta = header.pop("__metadata__")
    if meta.get("flashmat.format") != "flashmat-nmat":
        sys.exit(f"{path}: not a flashmat-nmat file")
    if meta.get("flashmat.version") not in ("1", "2", "3", "4"):
        sys.exit(f"{path}: unsupported version {meta.get('flashmat.version')}")
    body = data[8 + n :]
    crc = 0
    tensors = {}
    for name in sorted(header, key=lambda s: s.encode()):
        info = header[name]
        assert info["dtype"] == "F32"
        a, b = info["data_offsets"]
        raw = body[a:b]
        crc = zlib.crc32(name.encode(), crc)
        crc = zlib.crc32(raw, crc)
        tensors[name] = np.frombuffer(raw, dtype="<f4").reshape(info["shape"])
    if f"{crc:08x}" != meta["flashmat.crc32"]:
        sys.exit(f"{path}: checksum mismatch")
    return tensors, meta


def config_value(meta, key):
    # The config is flat TOML of `key = value` lines; no TOML library needed.
    for line in meta["config"].splitlines():
        k, _, v = line.partition("=")
        if k.strip() == key:
            return v.strip().strip('"')
    raise KeyError(key)


def normalize(v):
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def leaky(x, slope):
    return np.where(x >= 0, x, slope * x)


def encode(wi, wo, frequencies):
    """[R, 3] x 2 -> [R, 9 + 18 n]: v, sin(2^k pi v) (k-major), cos(...)."""
    v = np.concatenate([wi, wo, normalize(wi + wo)], axis=-1).astype(np.float64)
    scaled = v[:, None, :] * (2.0 ** np.arange(frequencies))[None, :, None]  # [R, n, 9]
    phase = np.pi * np.mod(scaled, 2.0)
    r = v.shape[0]
    return np.concatenate([v, np.sin(phase).reshape(r, -1), np.cos(phase).reshape(r, -1)], axis=-1)


def render(tensors, meta, light, view):
    """Linear radiance [3, H, W] for a point light and a camera (world units)."""
    nmap = tensors["neural_map"]
    c, h, w = nmap.shape
    # The shorter side spans [-1, 1], the longer [-a, a] (square pixels).
    xs = (2.0 * (np.arange(w) + 0.5) / w - 1.0) * (w / min(h, w))
    ys = (1.0 - 2.0 * (np.arange(h) + 0.5) / h) * (h / min(h, w))
    pos = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], np.zeros((h, w))), axis=-1).reshape(-1, 3)
    wi = normalize(np.asarray(light)[None, :] - pos)
    wo = normalize(np.asarray(view)[None, :] - pos)
    if "half_angle_feature = true" in meta["config"]:
        raise SystemExit("error: this material's renderer reads the log half-angle feature (compact-h / compact-f8h), which nmat_render.py does not implement")
    x = encode(wi, wo, int(config_value(meta, "enc_frequencies")))
    for i in range(3):  # ND_enc
        x = x @ tensors[f"renderer.nd_enc.{i}.weight"].T.astype(np.float64)
        if i < 2:
            x = leaky(x, 0.01)
    params = nmap.reshape(c, -1).T.astype(np.float64)
    x = np.concatenate([params, x], axis=-1)
    for i in range(7):  # M_render
        x = x @ tensors[f"renderer.m_render.{i}.weight"].T.astype(np.float64)
        if 1 <= i <= 5:
            x = leaky(x, 0.01)
        elif i == 6:
            x = leaky(x, 0.001)
    # Version 3: the material's exposure gain multiplies the network's radiance (1 before);
    # version 4: one per channel, a JSON array [r, g, b].
    gain = np.broadcast_to(np.asarray(json.loads(meta.get("gain", "1")), np.float64), (3,))
    radiance = np.maximum(np.expm1(np.minimum(x, 80.0)), 0.0) * gain  # [HW, 3]
    return radiance.T.reshape(3, h, w)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("nmat")
    ap.add_argument("--light", required=True)
    ap.add_argument("--view", default="0,0,%.9f" % (1.0 / np.tan(np.radians(14.0))))
    ap.add_argument("-o", "--output", help="write the render as .npy [3, H, W]")
    ap.add_argument("--compare", help="EXR or .npy render to compare with")
    a = ap.parse_args()
    tensors, meta = read_nmat(a.nmat)
    vec = lambda s: np.array([float(t) for t in s.split(",")])
    img = render(tensors, meta, vec(a.light), vec(a.view))
    if a.output:
        np.save(a.output, img.astype(np.float32))
    if a.compare:
        if a.compare.endswith(".npy"):
            ref = np.load(a.compare)
        else:
            import OpenEXR  # optional dependency

            f = OpenEXR.InputFile(a.compare)
            dw = f.header()["dataWindow"]
            hh, ww = dw.max.y - dw.min.y + 1, dw.max.x - dw.min.x + 1
            ref = np.stack([np.frombuffer(f.channel(ch), dtype=np.float32).reshape(hh, ww) for ch in "RGB"])
        # Compare the network outputs, ln(1 + R): f32 (flashmat) against f64 here.
        log_diff = np.abs(np.log1p(img) - np.log1p(ref))
        scale = np.abs(np.log1p(ref)).max()
        print(f"max |ln(1+R) difference| {log_diff.max():.3e} (largest ln(1+R) {scale:.3g}), median {np.median(log_diff):.3e}")


if __name__ == "__main__":
    main()
