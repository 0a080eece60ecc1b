#!/usr/bin/env python3
"""flashmat's neural BRDF in Mitsuba 3: the paper's sphere figure and a textured plane.

    python examples/mitsuba/render_examples.py OUT [--model models/flashmat.safetensors]
        [--spp 64] [--res 256] [--variant llvm_ad_rgb]

Steps (each skipped when its result is given with --svbrdf / --nmat):
 1. `flashmat svbrdf generate`: a procedural GGX material (its true maps) -> OUT/material/
 2. `flashmat render`: its co-located flash photo (linear EXR) -> OUT/photo.exr
 3. `flashmat estimate --model MODEL`: the neural material -> OUT/material.nmat
 4. OUT/spheres.png: three pixels of the estimated material on spheres under a
    point light (top row, `neural_brdf` in pixel mode) above the ground-truth
    GGX BRDF of the same pixels (bottom row, `flashmat_ggx`, flashmat's own
    GGX model: REFERENCE section 2).
 5. OUT/plane.png: the whole material on a plane (`texture` mode) seen by the
    input photo's camera, lit from the input light (left) and from the side
    (right); neural on top, ground truth below.
HDR versions (.exr, linear R) and timings.json go next to the PNGs. PNGs are
display-encoded like flashmat's: clamp(R^(1/2.2), 0, 1).

Normals: by default the sphere's shading frame plays the part of the
material frame, so both rows show the pixel's own normal perturbation (what
the network was trained on). --normal-correction reproduces the paper's
variant instead: the GGX spheres use the macro normal (0, 0, 1) and the
neural spheres rotate their directions by R = [u v n] (n = the pixel's true
normal), so that the normal the parameters encode faces outwards.
"""
import argparse
import gc
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(HERE))
import scenes  # noqa: E402

DEFAULT_MODEL = ROOT / "models" / "flashmat.safetensors"


class ExampleError(RuntimeError):
    """A problem with the inputs: reported as one line."""


def parse_pixels(text):
    """'ROW,COL ROW,COL ROW,COL' (or ';'-separated) -> [(row, col), ...]."""
    out = []
    for part in text.replace(";", " ").split():
        try:
            r, c = (int(x) for x in part.split(","))
        except ValueError:
            raise ExampleError(f"--pixels: expected ROW,COL triples like '10,20 30,40 50,60', got {part!r}")
        out.append((r, c))
    if len(out) != 3:
        raise ExampleError(f"--pixels: expected 3 pixels, got {len(out)}")
    return out


def find_flashmat(explicit):
    cands = [explicit] if explicit else []
    if os.environ.get("FLASHMAT_BIN"):
        cands.append(os.environ["FLASHMAT_BIN"])
    target = Path(os.environ.get("CARGO_TARGET_DIR", ROOT / "target"))
    cands += [str(target / "release" / "flashmat"), str(target / "debug" / "flashmat"), shutil.which("flashmat")]
    for c in cands:
        if c and Path(c).is_file() and os.access(c, os.X_OK):
            return c
    raise ExampleError("flashmat binary not found: build it (cargo build --release), or pass --flashmat / set FLASHMAT_BIN")


def run_flashmat(binary, *args):
    cmd = [binary, *map(str, args)]
    print("+", " ".join(cmd), flush=True)
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        msg = (r.stderr.strip() or r.stdout.strip()).splitlines()
        raise ExampleError(f"`flashmat {args[0]}` failed: {msg[-1] if msg else 'exit ' + str(r.returncode)}")


def pick_pixels(maps):
    """Three pixels spanning the material: the 2nd, 50th and 98th roughness
    percentiles (ties broken by the diffuse albedo), away from the border."""
    rough = maps["roughness"]
    h, w = rough.shape
    m = max(1, min(h, w) // 8)
    ii, jj = np.meshgrid(np.arange(m, h - m), np.arange(m, w - m), indexing="ij")
    ii, jj = ii.ravel(), jj.ravel()
    key = rough[ii, jj] + 1e-3 * maps["kd"][ii, jj].mean(-1)
    order = np.argsort(key, kind="stable")
    picks = [order[int(q * (len(order) - 1))] for q in (0.02, 0.5, 0.98)]
    return [(int(ii[k]), int(jj[k])) for k in picks]


def display(img):
    """flashmat's display encoding: clamp(R^(1/2.2), 0, 1) as 8-bit."""
    v = np.clip(np.maximum(img, 0.0) ** (1.0 / 2.2), 0.0, 1.0)
    return (v * 255.0 + 0.5).astype(np.uint8)


def grid(rows, gap=2):
    """Tiles [[img, ...], ...] (equal sizes, HxWx3) with `gap` black pixels between."""
    h, w, _ = rows[0][0].shape
    nr, nc = len(rows), len(rows[0])
    out = np.zeros((nr * h + (nr - 1) * gap, nc * w + (nc - 1) * gap, 3), np.float32)
    for r, row in enumerate(rows):
        for c, img in enumerate(row):
            out[r * (h + gap) : r * (h + gap) + h, c * (w + gap) : c * (w + gap) + w] = img
    return out


def write_images(mi, stem, hdr):
    mi.Bitmap(hdr.astype(np.float32)).write(str(stem.with_suffix(".exr")))
    mi.Bitmap(display(hdr)).write(str(stem.with_suffix(".png")))


def render(mi, scene_dict, seed=0, symbolic_calls=False):
    """Renders a scene dict; returns (HDR image [H, W, 3], seconds).

    Unless symbolic_calls, BSDF calls are evaluated ("wavefront") rather than
    traced into the render kernel as symbolic calls: on the LLVM backend the
    cooperative-vector network inside a symbolic call runs ~10x slower
    (docs/MITSUBA.md)."""
    import drjit as dr

    t0 = time.perf_counter()
    scene = mi.load_dict(scene_dict)
    with dr.scoped_set_flag(dr.JitFlag.SymbolicCalls, bool(symbolic_calls)):
        img = np.array(mi.render(scene, seed=seed), dtype=np.float64)[:, :, :3]
    dt = time.perf_counter() - t0
    # Free the scene: Mitsuba numbers live BSDF instances, and the number is
    # part of the traced kernel; reusing it lets the next scene reuse the kernel.
    del scene
    gc.collect()
    return img, dt


def parse_args(argv):
    ap = argparse.ArgumentParser(
        description="Render flashmat's neural BRDF in Mitsuba 3: sphere figure and textured plane.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    ap.add_argument("out", type=Path, help="output folder (created)")
    ap.add_argument("--model", type=Path, default=DEFAULT_MODEL, help="flashmat model file for `flashmat estimate`")
    ap.add_argument("--spp", type=int, default=64, help="samples per pixel")
    ap.add_argument("--res", type=int, default=256, help="width and height of each rendered view")
    ap.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (an RGB one)")
    ap.add_argument("--size", type=int, default=256, help="material and model resolution (multiple of 8)")
    ap.add_argument("--material", type=int, default=0, help="procedural material index (flashmat svbrdf generate --start)")
    ap.add_argument("--pixels", help="three pixels 'ROW,COL ROW,COL ROW,COL' (default: roughness percentiles)")
    ap.add_argument("--normal-correction", action="store_true", help="the paper's variant (see the module doc)")
    ap.add_argument("--flashmat", help="flashmat binary (default: $FLASHMAT_BIN, target/release, target/debug, PATH)")
    ap.add_argument("--svbrdf", type=Path, help="use this material folder instead of generating one")
    ap.add_argument("--nmat", type=Path, help="use this neural material instead of estimating one (needs --svbrdf)")
    ap.add_argument("--network", default="auto", choices=["auto", "coopvec", "unrolled"], help="neural_brdf network")
    ap.add_argument("--skip-plane", action="store_true", help="only the sphere figure")
    ap.add_argument("--symbolic-calls", action="store_true",
                    help="keep Dr.Jit's symbolic BSDF calls (Mitsuba's default; ~10x slower here on LLVM)")
    args = ap.parse_args(argv)
    if args.spp < 1 or args.res < 1:
        raise ExampleError("--spp and --res must be positive")
    if args.nmat and not args.svbrdf:
        raise ExampleError("--nmat needs --svbrdf (the true maps of the same material)")
    for name in ("svbrdf", "nmat"):
        p = getattr(args, name)
        if p is not None and not p.exists():
            raise ExampleError(f"--{name}: {p} does not exist")
    return args


def main(argv=None):
    args = parse_args(argv)
    out = args.out
    out.mkdir(parents=True, exist_ok=True)

    # 1-3: the material, its photo and its neural estimate.
    svbrdf, nmat = args.svbrdf, args.nmat
    if svbrdf is None or nmat is None:
        binary = find_flashmat(args.flashmat)
        if svbrdf is None:
            svbrdf = out / "material"
            if svbrdf.exists():
                shutil.rmtree(svbrdf)
            run_flashmat(binary, "svbrdf", "generate", "--count", 1, "--start", args.material,
                         "--size", args.size, "--out", svbrdf)
        if nmat is None:
            if not args.model.is_file():
                raise ExampleError(f"model {args.model} not found: pass --model (a `flashmat export` file)")
            photo = out / "photo.exr"
            run_flashmat(binary, "render", "--svbrdf", svbrdf, "-o", photo)
            nmat = out / "material.nmat"
            run_flashmat(binary, "estimate", photo, "--model", args.model, "--size", args.size, "-o", nmat)

    import mitsuba as mi

    if args.variant not in mi.variants():
        raise ExampleError(f"Mitsuba variant {args.variant!r} not available (have: {', '.join(mi.variants())})")
    mi.set_variant(args.variant)
    import flashmat.mitsuba as flashmat_mitsuba

    flashmat_mitsuba.register()
    maps = flashmat_mitsuba.load_svbrdf(svbrdf)
    nm = flashmat_mitsuba.read_nmat(nmat)
    if tuple(nm.resolution) != maps["roughness"].shape:
        raise ExampleError(
            f"{nmat} is {nm.resolution[1]}x{nm.resolution[0]} but the maps in {svbrdf} are "
            f"{maps['roughness'].shape[1]}x{maps['roughness'].shape[0]}: estimate at the material's size"
        )
    h, w = maps["roughness"].shape
    pixels = parse_pixels(args.pixels) if args.pixels else pick_pixels(maps)
    for r, c in pixels:
        if not (0 <= r < h and 0 <= c < w):
            raise ExampleError(f"--pixels: ({r},{c}) is outside the {w}x{h} material")

    timings = {"variant": args.variant, "res": args.res, "spp": args.spp, "symbolic_calls": args.symbolic_calls,
               "renders": []}
    neural_base = {"type": "neural_brdf", "filename": str(nmat), "network": args.network}

    # 4: the sphere figure.
    top, bottom = [], []
    for r, c in pixels:
        neural = dict(neural_base, mode="pixel", pixel_x=c, pixel_y=r)
        ggx = {"type": "flashmat_ggx", "svbrdf": str(svbrdf), "mode": "pixel", "pixel_x": c, "pixel_y": r}
        if args.normal_correction:
            neural["normal"] = mi.ScalarVector3f(*maps["normal"][r, c])
            ggx["flat"] = True
        for row, bsdf, kind in ((top, neural, "neural"), (bottom, ggx, "ggx")):
            img, dt = render(mi, scenes.sphere_scene(mi, bsdf, args.res, args.spp), symbolic_calls=args.symbolic_calls)
            row.append(img)
            timings["renders"].append({"scene": "sphere", "bsdf": kind, "pixel": [r, c], "seconds": dt})
            print(f"sphere {kind:6s} pixel ({r},{c}): {dt:.2f} s", flush=True)
    write_images(mi, out / "spheres", grid([top, bottom]))

    # 5: the plane.
    rows = []
    if not args.skip_plane:
        for kind, bsdf in (("neural", dict(neural_base, mode="texture")),
                           ("ggx", {"type": "flashmat_ggx", "svbrdf": str(svbrdf), "mode": "texture"})):
            row = []
            for lname, light in (("input", scenes.INPUT_LIGHT), ("side", scenes.SIDE_LIGHT)):
                img, dt = render(mi, scenes.plane_scene(mi, bsdf, light, args.res, args.spp),
                                 symbolic_calls=args.symbolic_calls)
                row.append(img)
                timings["renders"].append({"scene": "plane", "bsdf": kind, "light": lname, "seconds": dt})
                print(f"plane  {kind:6s} {lname} light: {dt:.2f} s", flush=True)
            rows.append(row)
        write_images(mi, out / "plane", grid(rows))

    for scene in ("sphere", "plane"):
        for kind in ("neural", "ggx"):
            ts = [t["seconds"] for t in timings["renders"] if t["scene"] == scene and t["bsdf"] == kind]
            if ts:
                timings[f"{scene}_{kind}_seconds"] = sum(ts)
    timings["pixels"] = pixels
    timings["normal_correction"] = args.normal_correction
    (out / "timings.json").write_text(json.dumps(timings, indent=1))
    print(f"wrote {out / 'spheres.png'}" + ("" if args.skip_plane else f" and {out / 'plane.png'}"))
    return {"pixels": pixels, "spheres": (top, bottom), "plane": rows, "timings": timings, "nmat": nmat, "svbrdf": svbrdf}


if __name__ == "__main__":
    try:
        main()
    except (ExampleError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)
