import json
import os
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

FIXTURES = Path(__file__).resolve().parents[2] / "tests" / "fixtures"
TINY_NMAT = FIXTURES / "tiny.nmat"
TINY_ROWS = FIXTURES / "tiny_rows.json"

# The `tiny` preset's sizes (src/model/config.rs).
TINY = dict(neural_channels=16, enc_frequencies=16, enc_hidden=32, enc_out=8, render_hidden=16, render_narrow=8)


def write_nmat(path, tensors, meta):
    """Writes a safetensors file with flashmat's integrity keys (for synthetic test materials)."""
    names = sorted(tensors, key=lambda s: s.encode())
    crc, offset, header, blobs = 0, 0, {}, []
    for name in names:
        raw = np.ascontiguousarray(tensors[name], dtype="<f4").tobytes()
        crc = zlib.crc32(raw, zlib.crc32(name.encode(), crc))
        header[name] = {"dtype": "F32", "shape": list(tensors[name].shape), "data_offsets": [offset, offset + len(raw)]}
        offset += len(raw)
        blobs.append(raw)
    meta = {"flashmat.format": "flashmat-nmat", "flashmat.version": "1", "flashmat.crc32": f"{crc:08x}", **meta}
    header["__metadata__"] = meta
    h = json.dumps(header).encode()
    h += b" " * (-len(h) % 8)
    Path(path).write_bytes(struct.pack("<Q", len(h)) + h + b"".join(blobs))


def synthetic_tensors(seed=0, h=8, w=8, sizes=TINY):
    rng = np.random.default_rng(seed)
    c, f = sizes["neural_channels"], sizes["enc_frequencies"]
    eh, eo, rh, rn = sizes["enc_hidden"], sizes["enc_out"], sizes["render_hidden"], sizes["render_narrow"]
    shapes = {
        "renderer.nd_enc.0.weight": (eh, 9 + 18 * f),
        "renderer.nd_enc.1.weight": (eh, eh),
        "renderer.nd_enc.2.weight": (eo, eh),
        "renderer.m_render.0.weight": (rh, c + eo),
        **{f"renderer.m_render.{i}.weight": (rh, rh) for i in range(1, 5)},
        "renderer.m_render.5.weight": (rn, rh),
        "renderer.m_render.6.weight": (3, rn),
    }
    t = {k: (rng.standard_normal(s) * np.sqrt(2.0 / s[1])).astype(np.float32) for k, s in shapes.items()}
    # Positive last layer: mostly positive outputs (R > 0), so comparisons test something.
    t["renderer.m_render.6.weight"] = np.abs(t["renderer.m_render.6.weight"])
    t["neural_map"] = rng.standard_normal((c, h, w)).astype(np.float32)
    t["input_photo"] = rng.random((3, h, w)).astype(np.float32)
    config = "name = \"tiny\"\n" + "".join(f"{k} = {v}\n" for k, v in sizes.items())
    meta = {"model_id": "tiny-synthetic", "config": config, "fov_deg": "28", "source": "synthetic.png",
            "ldr_input": "true", "resolution": json.dumps([h, w])}
    return t, meta


@pytest.fixture(scope="session")
def synthetic_nmat(tmp_path_factory):
    path = tmp_path_factory.mktemp("nmat") / "synthetic.nmat"
    t, meta = synthetic_tensors()
    write_nmat(path, t, meta)
    return path


def set_variant(name):
    import mitsuba as mi

    if name not in mi.variants():
        pytest.skip(f"Mitsuba variant {name} not available")
    mi.set_variant(name)
    import flashmat.mitsuba as flashmat_mitsuba

    flashmat_mitsuba.register()
    return mi


REPO = Path(__file__).resolve().parents[2]


def write_material(folder, h=32, w=32, seed=0):
    """A procedural GGX material as 8-bit PNGs in flashmat's MatFusion layout
    (folder/diffuse/0000001_diffuse.png, ...): smooth gradients of albedo and
    roughness, a gently varying normal. Returns the folder."""
    import mitsuba as mi

    rng = np.random.default_rng(seed)
    yy, xx = np.meshgrid(np.linspace(0, 1, h), np.linspace(0, 1, w), indexing="ij")
    kd = np.stack([0.2 + 0.6 * xx, 0.3 + 0.3 * yy, 0.15 + 0.1 * rng.random((h, w))], -1)
    ks = np.stack([0.04 + 0.3 * yy] * 3, -1)
    rough = 0.15 + 0.75 * (0.5 * xx + 0.5 * yy)
    n = np.stack([0.25 * np.sin(6 * xx), 0.2 * np.cos(5 * yy), np.ones((h, w))], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    enc = {
        "diffuse": kd ** (1 / 2.2), "specular": ks ** (1 / 2.2), "roughness": rough[:, :, None], "normals": (n + 1) / 2,
    }
    for name, img in enc.items():
        (Path(folder) / name).mkdir(parents=True, exist_ok=True)
        px = np.ascontiguousarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8))
        mi.Bitmap(px).write(str(Path(folder) / name / f"0000001_{name}.png"))
    return Path(folder)


def find_flashmat():
    """The flashmat binary ($FLASHMAT_BIN, then $CARGO_TARGET_DIR or target/, release then debug), or None."""
    import os

    cands = [os.environ.get("FLASHMAT_BIN")]
    target = Path(os.environ.get("CARGO_TARGET_DIR", REPO / "target"))
    cands += [target / "release" / "flashmat", target / "debug" / "flashmat"]
    for c in cands:
        if c and Path(c).is_file() and os.access(c, os.X_OK):
            return str(c)
    return None
