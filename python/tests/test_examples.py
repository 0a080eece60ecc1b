"""examples/mitsuba/render_examples.py at a tiny size (32x32 views, 4 spp,
the tiny fixture .nmat): its spheres and planes against analytic renders of
the same BRDFs (ray-sphere / ray-plane geometry in numpy, pixel centres)."""
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from conftest import REPO, TINY_NMAT, find_flashmat, set_variant, write_material
from flashmat.mitsuba.bsdf import correction_matrix
from flashmat.mitsuba.ggx import ggx_radiance, load_svbrdf
from flashmat.mitsuba.nmat import read_nmat, reference_log_radiance

EXAMPLES = REPO / "examples" / "mitsuba"
sys.path.insert(0, str(EXAMPLES))
import render_examples  # noqa: E402
import scenes  # noqa: E402

RES, SPP = 32, 4
needs_fixture = pytest.mark.skipif(not TINY_NMAT.exists(), reason="fixture missing")


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def camera_rays(origin, fov_deg, res, offsets=((0.5, 0.5),)):
    """Unit directions of rays through pixel positions (row-major, y up) of a camera
    at `origin` looking at the origin with up = +y (the scenes' cameras are on +z)."""
    t = math.tan(math.radians(fov_deg) / 2)
    out = []
    for ox, oy in offsets:
        col = (np.arange(res) + ox) / res * 2 - 1
        row = 1 - (np.arange(res) + oy) / res * 2
        x, y = np.meshgrid(col * t, row * t)
        out.append(unit(np.stack([x, y, -np.ones_like(x)], -1)))
    return out


def hit_sphere(origin, d):
    """Unit sphere at the origin: (hit mask, point)."""
    o = np.asarray(origin, np.float64)
    b = d @ o
    disc = b * b - (o @ o - 1.0)
    t = -b - np.sqrt(np.maximum(disc, 0))
    return disc > 0, o + t[..., None] * d


def sphere_reference(radiance_fn):
    """Analytic render of the sphere scene: radiance_fn(wi_local, wo_local) -> R [N, 3].
    The local frame is Mitsuba's for the y-pole sphere: s = normalize(y x n), t = n x s.
    Returns (image [RES, RES, 3], mask of pixels entirely on the sphere)."""
    cam = np.array(scenes.SPHERE_CAMERA)
    light = np.array(scenes.SPHERE_LIGHT)
    (d,) = camera_rays(cam, scenes.SPHERE_FOV, RES)
    hit, p = hit_sphere(cam, d)
    corners = camera_rays(cam, scenes.SPHERE_FOV, RES, offsets=((0, 0), (1, 0), (0, 1), (1, 1)))
    inside = hit & np.all([hit_sphere(cam, c)[0] for c in corners], axis=0)
    n = unit(p)
    s = unit(np.cross([0.0, 1.0, 0.0], n))
    t = np.cross(n, s)
    local = lambda v: np.stack([(v * s).sum(-1), (v * t).sum(-1), (v * n).sum(-1)], -1)
    to_light = light - p
    r2 = (to_light**2).sum(-1)
    wi, wo = local(unit(to_light)), local(unit(cam - p))
    lit = (wi[..., 2] > 0) & (wo[..., 2] > 0) & hit
    r0 = np.linalg.norm(light) - 1.0
    img = np.zeros((RES, RES, 3))
    img[lit] = radiance_fn(wi[lit], wo[lit]) * (r0 * r0 / r2[lit])[:, None]
    return img, inside


def plane_reference(radiance_fn, light, h, w):
    """Analytic render of the plane scene (RES x RES views of an h x w map):
    radiance_fn(pixel rows, cols, wi, wo) -> R."""
    d = scenes.INPUT_DISTANCE
    cam = np.array([0.0, 0.0, d])
    (rays,) = camera_rays(cam, 28.0, RES)
    p = cam + (d / -rays[..., 2])[..., None] * rays  # z = 0
    cols = np.clip(np.floor((p[..., 0] + 1) / 2 * w), 0, w - 1).astype(int)
    rows = np.clip(np.floor((1 - p[..., 1]) / 2 * h), 0, h - 1).astype(int)
    to_light = np.asarray(light) - p
    r2 = (to_light**2).sum(-1)
    r = radiance_fn(rows.ravel(), cols.ravel(), unit(to_light).reshape(-1, 3), unit(cam - p).reshape(-1, 3))
    return r.reshape(RES, RES, 3) * (np.dot(light, light) / r2)[..., None]


def close(img, ref, mask, median_bound, name):
    """Pixel-jittered Monte Carlo vs pixel-centre analytic: median relative error + correlation."""
    a, b = img[mask].ravel(), ref[mask].ravel()
    sel = b > 0.01 * np.median(b[b > 0])  # not the terminator's near-zero values
    rel = np.abs(a[sel] - b[sel]) / b[sel]
    assert sel.sum() > 50, f"{name}: only {sel.sum()} lit values"
    assert np.median(rel) < median_bound, f"{name}: median relative error {np.median(rel):.4f}"
    assert np.corrcoef(a, b)[0, 1] > 0.98, f"{name}: correlation {np.corrcoef(a, b)[0, 1]:.4f}"
    assert np.all(np.isfinite(img))


@pytest.fixture(scope="module")
def example(tmp_path_factory):
    set_variant("llvm_ad_rgb")
    tmp = tmp_path_factory.mktemp("example")
    folder = write_material(tmp / "material", 32, 32)
    out = tmp / "out"
    result = render_examples.main([str(out), "--svbrdf", str(folder), "--nmat", str(TINY_NMAT),
                                   "--res", str(RES), "--spp", str(SPP)])
    return result, out, load_svbrdf(folder), read_nmat(TINY_NMAT)


@needs_fixture
def test_example_writes_pngs(example):
    import mitsuba as mi

    result, out, maps, _ = example
    sph = np.array(mi.Bitmap(str(out / "spheres.png")))
    assert sph.shape == (2 * RES + 2, 3 * RES + 4, 3) and sph.dtype == np.uint8
    pl = np.array(mi.Bitmap(str(out / "plane.png")))
    assert pl.shape == (2 * RES + 2, 2 * RES + 2, 3)
    # The PNG is the display encoding of the HDR image next to it.
    hdr = np.array(mi.Bitmap(str(out / "spheres.exr")))
    assert np.abs(render_examples.display(hdr).astype(int) - sph.astype(int)).max() <= 1
    t = json.loads((out / "timings.json").read_text())
    assert len(t["renders"]) == 10 and all(r["seconds"] > 0 for r in t["renders"])
    # Three distinct pixels, spread over the roughness range.
    rough = sorted(maps["roughness"][r, c] for r, c in result["pixels"])
    assert rough[2] - rough[0] > 0.2


@needs_fixture
def test_example_ggx_spheres_match_analytic(example):
    result, _, maps, _ = example
    top, bottom = result["spheres"]
    for (r, c), img in zip(result["pixels"], bottom):
        kd, ks, ro, n = maps["kd"][r, c], maps["ks"][r, c], maps["roughness"][r, c], maps["normal"][r, c]
        fn = lambda wi, wo: ggx_radiance(np.tile(kd, (len(wi), 1)), np.tile(ks, (len(wi), 1)), np.full(len(wi), ro),
                                         np.tile(n, (len(wi), 1)), wi, wo)
        ref, inside = sphere_reference(fn)
        close(img, ref, inside, 0.03, f"GGX sphere {(r, c)}")
        # Lit side (towards the light, upper left) brighter than the far side.
        assert img[RES // 3, RES // 3].mean() > 2 * img[2 * RES // 3, 2 * RES // 3].mean()


@needs_fixture
def test_example_neural_spheres_match_reference(example):
    result, _, _, nm = example
    top, _ = result["spheres"]
    for (r, c), img in zip(result["pixels"], top):
        p = nm.neural_map[:, r, c].astype(np.float64)
        fn = lambda wi, wo: np.maximum(np.expm1(reference_log_radiance(nm, np.tile(p, (len(wi), 1)), wi, wo)), 0)
        ref, inside = sphere_reference(fn)
        close(img, ref, inside, 0.05, f"neural sphere {(r, c)}")


@needs_fixture
def test_example_planes_match_analytic(example):
    result, _, maps, nm = example
    (neural_in, neural_side), (ggx_in, ggx_side) = result["plane"]
    h, w = maps["roughness"].shape
    ggx = lambda i, j, wi, wo: ggx_radiance(maps["kd"][i, j], maps["ks"][i, j], maps["roughness"][i, j],
                                            maps["normal"][i, j], wi, wo)
    neural = lambda i, j, wi, wo: np.maximum(np.expm1(reference_log_radiance(
        nm, nm.neural_map[:, i, j].T.astype(np.float64), wi, wo)), 0)
    everywhere = np.ones((RES, RES), bool)
    for img, fn, light, name in ((ggx_in, ggx, scenes.INPUT_LIGHT, "GGX input"),
                                 (ggx_side, ggx, scenes.SIDE_LIGHT, "GGX side"),
                                 (neural_in, neural, scenes.INPUT_LIGHT, "neural input"),
                                 (neural_side, neural, scenes.SIDE_LIGHT, "neural side")):
        close(img, plane_reference(fn, light, h, w), everywhere, 0.05, name)


@needs_fixture
def test_example_normal_correction(tmp_path):
    """--normal-correction: GGX spheres with the macro normal, neural spheres fed R d."""
    set_variant("llvm_ad_rgb")
    folder = write_material(tmp_path / "material", 32, 32)
    maps = load_svbrdf(folder)
    nm = read_nmat(TINY_NMAT)
    result = render_examples.main([str(tmp_path / "out"), "--svbrdf", str(folder), "--nmat", str(TINY_NMAT),
                                   "--res", str(RES), "--spp", str(SPP), "--skip-plane", "--normal-correction",
                                   "--pixels", "5,20 16,16 26,8"])
    assert result["pixels"] == [(5, 20), (16, 16), (26, 8)]
    top, bottom = result["spheres"]
    r, c = 5, 20
    n = maps["normal"][r, c]
    assert n[2] < 0.99  # a tilted pixel normal
    fn = lambda wi, wo: ggx_radiance(np.tile(maps["kd"][r, c], (len(wi), 1)), np.tile(maps["ks"][r, c], (len(wi), 1)),
                                     np.full(len(wi), maps["roughness"][r, c]), np.tile([0, 0, 1.0], (len(wi), 1)), wi, wo)
    ref, inside = sphere_reference(fn)
    close(bottom[0], ref, inside, 0.03, "flat GGX sphere")
    rot = correction_matrix(n)
    p = nm.neural_map[:, r, c].astype(np.float64)
    fn = lambda wi, wo: np.maximum(np.expm1(reference_log_radiance(nm, np.tile(p, (len(wi), 1)), wi @ rot.T, wo @ rot.T)), 0)
    ref, inside = sphere_reference(fn)
    close(top[0], ref, inside, 0.05, "corrected neural sphere")


def test_example_bad_inputs(tmp_path):
    with pytest.raises(render_examples.ExampleError, match="expected 3 pixels"):
        render_examples.parse_pixels("1,2 3,4")
    with pytest.raises(render_examples.ExampleError, match="ROW,COL"):
        render_examples.parse_pixels("1,2 3;4 5")
    with pytest.raises(render_examples.ExampleError, match="--nmat needs --svbrdf"):
        render_examples.parse_args([str(tmp_path), "--nmat", str(TINY_NMAT)])
    with pytest.raises(render_examples.ExampleError, match="does not exist"):
        render_examples.parse_args([str(tmp_path), "--svbrdf", str(tmp_path / "nope")])
    # From the command line: one line on stderr, exit code 2.
    r = subprocess.run([sys.executable, str(EXAMPLES / "render_examples.py"), str(tmp_path / "o"),
                        "--svbrdf", str(tmp_path), "--nmat", str(TINY_NMAT)], capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().count("\n") == 0 and "not a material folder" in r.stderr, r.stderr


@pytest.mark.skipif(find_flashmat() is None, reason="flashmat binary not built (cargo build)")
def test_example_end_to_end_with_flashmat(tmp_path):
    """The whole pipeline: flashmat svbrdf generate, render, estimate (a tiny model
    trained for one step and exported), then both scenes."""
    set_variant("llvm_ad_rgb")
    exe = find_flashmat()
    run = lambda *a: subprocess.run([exe, *map(str, a)], check=True, capture_output=True)
    run("train", "--preset", "tiny", "--steps", 1, "--crop", 32, "--threads", 1, "--out", tmp_path / "run")
    run("export", "--run", tmp_path / "run", "-o", tmp_path / "tiny.safetensors")
    out = tmp_path / "out"
    result = render_examples.main([str(out), "--model", str(tmp_path / "tiny.safetensors"), "--size", "32",
                                   "--res", "16", "--spp", "1", "--flashmat", exe])
    for f in ("material.nmat", "photo.exr", "spheres.png", "plane.png", "material/diffuse/0000001_diffuse.png"):
        assert (out / f).is_file(), f
    nm = read_nmat(out / "material.nmat")
    assert nm.resolution == (32, 32) and nm.config["name"] == "tiny"
    top, bottom = result["spheres"]
    assert all(np.all(np.isfinite(x)) for x in top + bottom)
    assert all(x.max() > 0 for x in bottom)
    # A missing model: one clear error.
    with pytest.raises(render_examples.ExampleError, match="model .* not found"):
        render_examples.main([str(tmp_path / "o2"), "--model", str(tmp_path / "none.safetensors"),
                              "--size", "32", "--flashmat", exe])
