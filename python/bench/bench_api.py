"""The Python API's cost over the library's own calls, in one process.

    python python/bench/bench_api.py [--size 256] [--runs 20] [--device cpu]

For the same frame, times `material.render(light, view)` (under
torch.no_grad) against the library's render that `flashmat relight` runs,
and `model.estimate(photo)` against the library calls `flashmat estimate`
makes, alternating the two so that both see the same machine state.
Reports medians and their ratio (target: at most 1.05). Build the package
in the release profile for figures (FLASHMAT_PY_PROFILE=release
scripts/test_python.sh, or pip install --no-build-isolation .).
"""
import argparse
import statistics
import time
from pathlib import Path

import torch

import flashmat
from flashmat import _flashmat

PHOTO = Path(__file__).resolve().parents[2] / "examples" / "photos" / "IMG_20180104_210434.png"


def timed(f):
    t0 = time.perf_counter()
    out = f()
    if isinstance(out, torch.Tensor) and out.is_cuda:
        torch.cuda.synchronize()
    return time.perf_counter() - t0


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--runs", type=int, default=20)
    ap.add_argument("--estimate-runs", type=int, default=5)
    ap.add_argument("--device", default="cpu")
    a = ap.parse_args()
    model = flashmat.load_model(device=a.device)
    material = model.estimate(PHOTO, size=a.size)
    light, view = (0.8, -0.5, 2.5), (0.3, 0.2, 3.0)
    rows = []
    with torch.no_grad():
        material.render(light, view)  # warm-up of both paths
        _flashmat._library_render_seconds(material, light, view, 1)
        py, lib = [], []
        for _ in range(a.runs):
            py.append(timed(lambda: material.render(light, view)))
            lib += _flashmat._library_render_seconds(material, light, view, 1)
        rows.append(("render", py, lib))
        py, lib = [], []
        for _ in range(a.estimate_runs):
            py.append(timed(lambda: model.estimate(PHOTO, size=a.size)))
            lib += _flashmat._library_estimate_seconds(model, str(PHOTO), a.size, 1)
        rows.append(("estimate", py, lib))
    print(f"flashmat Python API vs the library's own calls, {a.size}x{a.size}, {a.device}, torch threads {torch.get_num_threads()}")
    print("| call | Python (median s) | library (median s) | ratio |")
    print("|---|---|---|---|")
    for name, py, lib in rows:
        p, l = statistics.median(py), statistics.median(lib)
        print(f"| {name} | {p:.4f} | {l:.4f} | {p / l:.3f} |")


if __name__ == "__main__":
    main()
