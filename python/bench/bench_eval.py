"""BSDF evaluations per second of neural_brdf (llvm_ad_rgb by default).

    python python/bench/bench_eval.py --preset compact --network coopvec
    python python/bench/bench_eval.py --nmat material.nmat --mode pixel

--preset writes a randomly initialised .nmat of that preset's sizes (speed
does not depend on the weight values); --nmat uses a given file (default:
the tiny fixture). Each run calls `eval` on N random (uv, wi, wo) and waits
for the result; run 0 includes tracing and the kernel compile (or Dr.Jit's
kernel-cache load), later runs are the steady state.
"""
import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "python" / "tests"))

PRESETS = {  # src/model/config.rs
    "tiny": dict(neural_channels=16, enc_frequencies=16, enc_hidden=32, enc_out=8, render_hidden=16, render_narrow=8),
    "compact": dict(neural_channels=64, enc_frequencies=16, enc_hidden=128, enc_out=32, render_hidden=64, render_narrow=32),
    "paper": dict(neural_channels=64, enc_frequencies=16, enc_hidden=594, enc_out=32, render_hidden=128, render_narrow=64),
}


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", choices=sorted(PRESETS), help="random material of this preset's sizes")
    ap.add_argument("--nmat", help="a .nmat file (default: tests/fixtures/tiny.nmat)")
    ap.add_argument("--network", default="auto", choices=["auto", "coopvec", "unrolled"])
    ap.add_argument("--mode", default="texture", choices=["texture", "pixel"])
    ap.add_argument("--n", type=int, default=1 << 18, help="evaluations per run")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--numpy", action="store_true",
                    help="instead: the same network as batched float32 numpy matmuls (BLAS GEMM), for comparison")
    args = ap.parse_args()

    import drjit as dr
    import mitsuba as mi

    mi.set_variant(args.variant)
    import flashmat.mitsuba as flashmat_mitsuba

    flashmat_mitsuba.register()
    if args.preset:
        from conftest import synthetic_tensors, write_nmat

        tmp = tempfile.mkdtemp()
        nmat = str(Path(tmp) / f"{args.preset}.nmat")
        t, meta = synthetic_tensors(seed=0, h=64, w=64, sizes=PRESETS[args.preset])
        write_nmat(nmat, t, meta)
    else:
        nmat = args.nmat or str(ROOT / "tests/fixtures/tiny.nmat")
    if args.numpy:
        return bench_numpy(flashmat_mitsuba.read_nmat(nmat), args.n, args.runs)
    bsdf = mi.load_dict({"type": "neural_brdf", "filename": nmat, "mode": args.mode, "network": args.network})
    print(bsdf)
    n = args.n
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
    for rep in range(args.runs):
        t0 = time.time()
        v = bsdf.eval(mi.BSDFContext(), si, wo)
        dr.eval(v)
        dr.sync_thread()
        dt = time.time() - t0
        note = " (includes trace + compile or kernel-cache load)" if rep == 0 else ""
        print(f"run {rep}: {n} evals in {dt:.3f} s = {n / dt / 1e6:.3f} M evals/s{note}", flush=True)


def bench_numpy(nm, n, runs):
    """ND_enc + M_render of n random rows as float32 GEMMs (what a batched,
    matrix-friendly evaluation outside the path tracer's kernel would cost)."""
    rng = np.random.default_rng(0)
    c, h, w = nm.neural_map.shape
    wi, wo = rng.standard_normal((2, n, 3)).astype(np.float32)
    wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]) + 0.05, np.abs(wo[:, 2]) + 0.05
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    params = nm.neural_map.reshape(c, -1).T[rng.integers(0, h * w, n)].astype(np.float32)
    enc = [m.T.astype(np.float32).copy() for m in nm.nd_enc]
    ren = [m.T.astype(np.float32).copy() for m in nm.m_render]
    lk = lambda x, s: np.maximum(x, s * x)
    for rep in range(runs):
        t0 = time.time()
        hv = wi + wo
        hv /= np.linalg.norm(hv, axis=1, keepdims=True)
        v = np.concatenate([wi, wo, hv], 1)
        ph = np.pi * np.mod(v[:, None, :] * (2.0 ** np.arange(nm.frequencies, dtype=np.float32))[None, :, None], 2.0)
        x = np.concatenate([v, np.sin(ph).reshape(n, -1), np.cos(ph).reshape(n, -1)], 1)
        x = lk(x @ enc[0], 0.01)
        x = lk(x @ enc[1], 0.01)
        y = np.concatenate([params, x @ enc[2]], 1) @ ren[0]
        for m in ren[1:-1]:
            y = lk(y @ m, 0.01)
        out = lk(y @ ren[-1], 0.001)
        dt = time.time() - t0
        print(f"numpy run {rep}: {n} evals in {dt:.3f} s = {n / dt / 1e6:.3f} M evals/s ({out.shape})", flush=True)


if __name__ == "__main__":
    main()
