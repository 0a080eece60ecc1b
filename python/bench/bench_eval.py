"""BSDF evaluations per second of neural_brdf (llvm_ad_rgb), texture mode, on
the tiny fixture material: python python/bench/bench_eval.py [N] [NMAT]."""
import sys
import time
from pathlib import Path

import numpy as np
import drjit as dr
import mitsuba as mi

mi.set_variant("llvm_ad_rgb")
import flashmat_mitsuba  # noqa: E402

flashmat_mitsuba.register()
n = int(sys.argv[1]) if len(sys.argv) > 1 else 1 << 20
nmat = sys.argv[2] if len(sys.argv) > 2 else str(Path(__file__).resolve().parents[2] / "tests/fixtures/tiny.nmat")
bsdf = mi.load_dict({"type": "neural_brdf", "filename": nmat, "mode": "texture"})
rng = np.random.default_rng(0)


def dirs():
    v = rng.standard_normal((n, 3))
    v[:, 2] = np.abs(v[:, 2]) + 0.05
    return mi.Vector3f((v / np.linalg.norm(v, axis=1, keepdims=True)).T.astype(np.float32))


si = dr.zeros(mi.SurfaceInteraction3f, n)
si.uv = mi.Point2f(rng.random((2, n)).astype(np.float32))
si.wi = dirs()
wo = dirs()
dr.eval(si, wo)
for rep in range(3):
    t0 = time.time()
    v = bsdf.eval(mi.BSDFContext(), si, wo)
    dr.eval(v)
    dr.sync_thread()
    dt = time.time() - t0
    print(f"run {rep}: {n} evals in {dt:.3f} s = {n / dt / 1e6:.2f} M evals/s" + (" (includes trace + compile/cache load)" if rep == 0 else ""))
