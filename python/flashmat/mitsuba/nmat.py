"""Reader of flashmat `.nmat` neural materials (docs/NMAT.md), numpy only.

No safetensors, torch or flashmat needed: the container is parsed by hand
(8-byte little-endian header length, JSON header, raw little-endian f32
tensors) and its integrity keys (format tag, version, CRC-32) are checked.
Every problem raises :class:`NmatError` (a ``ValueError``) naming the file.
"""
import json
import struct
import zlib
from dataclasses import dataclass

import numpy as np

NMAT_FORMAT = "flashmat-nmat"
NMAT_VERSION = "4"
# Version 2 allows rectangular maps (a renderer-side geometry change only:
# per-pixel parameters and the network are read the same way); version 3
# adds the exposure `gain` (1 when absent); version 4 makes it one per
# channel (a JSON array [r, g, b]: the white balance), so all four are read.
NMAT_READABLE_VERSIONS = ("1", "2", "3", "4")
CONFIG_INT_KEYS = ("neural_channels", "enc_frequencies", "enc_hidden", "enc_out", "render_hidden", "render_narrow")


class NmatError(ValueError):
    """A file that is not a readable flashmat .nmat (version 1, 2, 3 or 4)."""


@dataclass
class Nmat:
    path: str
    neural_map: np.ndarray  # [C, H, W] float32, row 0 = top
    nd_enc: list  # 3 weight matrices [out, in] float32
    m_render: list  # 7 weight matrices [out, in] float32
    config: dict  # the sizes (ints) and "name"
    meta: dict  # all metadata strings
    gain: tuple = (1.0, 1.0, 1.0)  # exposure per channel: renders are the network's radiance times this

    @property
    def channels(self):
        return self.neural_map.shape[0]

    @property
    def resolution(self):
        return self.neural_map.shape[1:]

    @property
    def frequencies(self):
        return self.config["enc_frequencies"]


def parse_config(text):
    """The flat TOML `key = value` lines of the `config` metadata."""
    out = {}
    for line in text.splitlines():
        k, sep, v = line.partition("=")
        if not sep:
            continue
        v = v.strip()
        if v in ("true", "false"):
            out[k.strip()] = v == "true"
        else:
            out[k.strip()] = v.strip('"') if v.startswith('"') else int(v)
    return out


def header_crc(header, meta):
    """CRC-32 of tensor names, dtypes, shapes and the metadata (docs/NMAT.md, `flashmat.meta_crc32`)."""
    h = 0
    for name in sorted(header, key=lambda s: s.encode("utf-8")):
        info = header[name]
        for field in (name, str(info["dtype"]), ",".join(str(int(d)) for d in info["shape"])):
            h = zlib.crc32(field.encode("utf-8") + b"\0", h)
    for key in sorted(meta, key=lambda s: s.encode("utf-8")):
        if key != "flashmat.meta_crc32":
            h = zlib.crc32(key.encode("utf-8") + b"\0" + str(meta[key]).encode("utf-8") + b"\0", h)
    return h


def read_nmat(path):
    """Reads and verifies a .nmat file; returns an :class:`Nmat`."""
    path = str(path)

    def fail(msg):
        raise NmatError(f"{path}: {msg}")

    try:
        with open(path, "rb") as f:
            data = f.read()
    except OSError as e:
        raise NmatError(f"{path}: cannot read: {e.strerror or e}") from e
    if len(data) < 8:
        fail("not a flashmat .nmat file (too short for a safetensors header)")
    (n,) = struct.unpack("<Q", data[:8])
    if n < 2 or 8 + n > len(data):
        fail("not a flashmat .nmat file (bad safetensors header length)")
    try:
        header = json.loads(data[8 : 8 + n].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError):
        fail("not a flashmat .nmat file (safetensors header is not JSON)")
    if not isinstance(header, dict):
        fail("not a flashmat .nmat file (safetensors header is not a JSON object)")
    meta = header.pop("__metadata__", None)
    if not isinstance(meta, dict):
        fail("not a flashmat .nmat file (no metadata)")
    # A damaged key name must not switch a check off: unknown `flashmat.`
    # keys, or keys one byte away from an integrity key, are damage.
    integrity = ("flashmat.format", "flashmat.version", "flashmat.crc32", "flashmat.meta_crc32")
    for key in meta:
        near = any(len(key) == len(k) and sum(a != b for a, b in zip(key, k)) == 1 for k in integrity)
        if key not in integrity and (key.startswith("flashmat.") or near):
            fail(f"unknown integrity field {key!r}: the file is damaged")
    fmt = meta.get("flashmat.format")
    if fmt != NMAT_FORMAT:
        fail(f"not a flashmat .nmat file (format tag {fmt!r}, expected {NMAT_FORMAT!r})")
    if meta.get("flashmat.version") not in NMAT_READABLE_VERSIONS:
        fail(f"unsupported .nmat version {meta.get('flashmat.version')!r} (this reader knows versions 1, 2 and 3)")
    body = data[8 + n :]
    crc = 0
    tensors = {}
    for name in sorted(header, key=lambda s: s.encode("utf-8")):
        info = header[name]
        try:
            dtype, shape, (a, b) = info["dtype"], [int(s) for s in info["shape"]], info["data_offsets"]
        except (KeyError, TypeError, ValueError):
            fail(f"malformed entry for tensor {name!r}")
        if dtype != "F32":
            fail(f"tensor {name!r} has dtype {dtype}, expected F32")
        if not (0 <= a <= b <= len(body)) or b - a != 4 * int(np.prod(shape, dtype=np.int64)):
            fail(f"tensor {name!r} lies outside the file or has the wrong size (truncated?)")
        raw = body[a:b]
        crc = zlib.crc32(name.encode("utf-8"), crc)
        crc = zlib.crc32(raw, crc)
        tensors[name] = np.frombuffer(raw, dtype="<f4").reshape(shape)
    if f"{crc:08x}" != meta.get("flashmat.crc32"):
        fail(f"checksum mismatch (stored {meta.get('flashmat.crc32')!r}, computed {crc:08x}): the file is damaged")
    if "flashmat.meta_crc32" in meta and f"{header_crc(header, meta):08x}" != meta["flashmat.meta_crc32"]:
        fail("header checksum mismatch (shapes or metadata): the file is damaged")
    try:
        config = parse_config(meta["config"])
        sizes = {k: int(config[k]) for k in CONFIG_INT_KEYS}
    except (KeyError, ValueError) as e:
        fail(f"bad or missing `config` metadata ({e})")
    config.update(sizes)
    if config.get("half_angle_feature"):
        fail("its renderer reads the log half-angle feature (a compact-h / compact-f8h model, issue 48), which this plugin does not implement")
    c, f = sizes["neural_channels"], sizes["enc_frequencies"]
    eh, eo, rh, rn = sizes["enc_hidden"], sizes["enc_out"], sizes["render_hidden"], sizes["render_narrow"]
    expected = {
        "renderer.nd_enc.0.weight": [eh, 9 + 18 * f],
        "renderer.nd_enc.1.weight": [eh, eh],
        "renderer.nd_enc.2.weight": [eo, eh],
        "renderer.m_render.0.weight": [rh, c + eo],
        **{f"renderer.m_render.{i}.weight": [rh, rh] for i in range(1, 5)},
        "renderer.m_render.5.weight": [rn, rh],
        "renderer.m_render.6.weight": [3, rn],
    }
    for name, shape in expected.items():
        if name not in tensors:
            fail(f"missing tensor {name!r}")
        if list(tensors[name].shape) != shape:
            fail(f"tensor {name!r} has shape {list(tensors[name].shape)}, expected {shape}")
    nmap = tensors.get("neural_map")
    if nmap is None or nmap.ndim != 3 or nmap.shape[0] != c:
        fail(f"missing or malformed `neural_map` (expected [{c}, H, W])")
    gain = parse_gain(meta.get("gain", "1"))
    if gain is None:
        fail(f"metadata field 'gain' must be a positive number or three of them ([r, g, b]), got {meta.get('gain')!r}")
    return Nmat(
        path=path,
        neural_map=nmap,
        nd_enc=[tensors[f"renderer.nd_enc.{i}.weight"] for i in range(3)],
        m_render=[tensors[f"renderer.m_render.{i}.weight"] for i in range(7)],
        config=config,
        meta=meta,
        gain=gain,
    )


def parse_gain(text):
    """The `gain` metadata as (r, g, b): one number (version 3) or a JSON array of three (version 4); None if invalid."""
    try:
        value = json.loads(text)
    except ValueError:
        return None
    values = [value] * 3 if isinstance(value, (int, float)) and not isinstance(value, bool) else value
    if not isinstance(values, list) or len(values) != 3:
        return None
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v > 0 for v in values):
        return None
    return tuple(float(v) for v in values)


def leaky(x, slope):
    return np.where(x >= 0, x, slope * x)


def half_vector_f32(wi, wo):
    """h = normalize(wi + wo) rounded exactly as flashmat computes it in f32
    (s = wi + wo; s / sqrt((s.x^2 + s.y^2) + s.z^2)). The encoding's top
    frequency multiplies h by 2^15 pi, so the last bit of h matters."""
    s = np.asarray(wi, np.float32) + np.asarray(wo, np.float32)
    sq = s * s
    n = np.sqrt((sq[..., 0:1] + sq[..., 1:2]) + sq[..., 2:3])
    return s / np.maximum(n, np.float32(1e-12))


def reference_log_radiance(nm, params, wi, wo, f32_half=True):
    """numpy M_render output ln(1 + R) for rows: params [R, C], wi/wo [R, 3]
    (wi towards the light, wo towards the camera). Same math as
    scripts/nmat_render.py, in f64 except for the half vector, which is
    computed in f32 like flashmat when f32_half (see half_vector_f32)."""
    if f32_half:
        h = half_vector_f32(wi, wo).astype(np.float64)
    wi, wo = np.asarray(wi, np.float64), np.asarray(wo, np.float64)
    if not f32_half:
        h = wi + wo
        h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
    v = np.concatenate([wi, wo, h], axis=-1)
    scaled = v[:, None, :] * (2.0 ** np.arange(nm.frequencies))[None, :, None]
    phase = np.pi * np.mod(scaled, 2.0)
    r = v.shape[0]
    x = np.concatenate([v, np.sin(phase).reshape(r, -1), np.cos(phase).reshape(r, -1)], axis=-1)
    for i, w in enumerate(nm.nd_enc):
        x = x @ w.T.astype(np.float64)
        if i < 2:
            x = leaky(x, 0.01)
    x = np.concatenate([np.asarray(params, np.float64), x], axis=-1)
    for i, w in enumerate(nm.m_render):
        x = x @ w.T.astype(np.float64)
        if 1 <= i <= 5:
            x = leaky(x, 0.01)
        elif i == 6:
            x = leaky(x, 0.001)
    return x
