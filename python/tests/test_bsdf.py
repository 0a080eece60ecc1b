"""The neural_brdf plugin against flashmat's own M_render output (fixture
rows written by `flashmat nmat-rows`), its sampling and its options.

LLVM kernels of the unrolled networks take ~20-30 s each to compile the first
time (Dr.Jit caches them on disk, ~/.drjit, afterwards)."""
import json
import math

import numpy as np
import pytest

from conftest import TINY_NMAT, TINY_ROWS, set_variant
from flashmat.mitsuba.bsdf import correction_matrix
from flashmat.mitsuba.nmat import read_nmat, reference_log_radiance

needs_fixture = pytest.mark.skipif(not (TINY_NMAT.exists() and TINY_ROWS.exists()), reason="fixture missing")
RTOL = 1e-4


def load_rows():
    doc = json.loads(TINY_ROWS.read_text())
    rows = doc["rows"]
    get = lambda k: np.array([r[k] for r in rows], dtype=np.float32)
    return np.array([r["pixel"] for r in rows]), get("params"), get("wi"), get("wo"), get("out").astype(np.float64)


def pixel_uv(pix, h, w):
    """UV of the centre of pixel (row i, column j): u = (j + 0.5) / W, v = 1 - (i + 0.5) / H."""
    return (pix[:, 1] + 0.5) / w, 1.0 - (pix[:, 0] + 0.5) / h


def check_radiance(value_over_pi, out):
    """eval returns R / pi; R = max(exp(out) - 1, 0) from flashmat's out = ln(1 + R)."""
    r_plugin = np.asarray(value_over_pi, np.float64) * math.pi
    r_ref = np.maximum(np.expm1(out), 0.0)
    np.testing.assert_allclose(r_plugin, r_ref, rtol=RTOL, atol=1e-6)


@needs_fixture
def test_fixture_params_match_map():
    pix, params, *_ = load_rows()
    nm = read_nmat(TINY_NMAT)
    np.testing.assert_array_equal(nm.neural_map[:, pix[:, 0], pix[:, 1]].T, params)


@needs_fixture
def test_numpy_reference_matches_flashmat():
    _, params, wi, wo, out = load_rows()
    ref = reference_log_radiance(read_nmat(TINY_NMAT), params, wi, wo)
    np.testing.assert_allclose(ref, out, rtol=RTOL, atol=RTOL)


@needs_fixture
def test_scalar_rgb_matches_flashmat_rows():
    mi = set_variant("scalar_rgb")
    pix, params, wi, wo, out = load_rows()
    nm = read_nmat(TINY_NMAT)
    h, w = nm.resolution
    u, v = pixel_uv(pix, h, w)
    ctx = mi.BSDFContext()
    tex = mi.load_dict({"type": "neural_brdf", "filename": str(TINY_NMAT), "mode": "texture"})
    vals, logs = [], []
    for k in range(len(out)):
        si = mi.SurfaceInteraction3f()
        si.uv = mi.Point2f(float(u[k]), float(v[k]))
        si.wi = mi.Vector3f(*wo[k])  # Mitsuba's si.wi: towards the camera
        vals.append(np.array(tex.eval(ctx, si, mi.Vector3f(*wi[k]))))  # wo: towards the light
        pixel = mi.load_dict(
            {"type": "neural_brdf", "filename": str(TINY_NMAT), "pixel_x": int(pix[k, 1]), "pixel_y": int(pix[k, 0])}
        )
        logs.append(np.array(pixel.log_radiance(None, mi.Vector3f(*wi[k]), mi.Vector3f(*wo[k]))))
    np.testing.assert_allclose(np.array(logs), out, rtol=RTOL, atol=RTOL)
    check_radiance(np.array(vals), out)


@needs_fixture
def test_llvm_texture_matches_flashmat_rows():
    mi = set_variant("llvm_ad_rgb")
    import drjit as dr

    pix, params, wi, wo, out = load_rows()
    nm = read_nmat(TINY_NMAT)
    h, w = nm.resolution
    u, v = pixel_uv(pix, h, w)
    bsdf = mi.load_dict({"type": "neural_brdf", "filename": str(TINY_NMAT), "mode": "texture"})
    si = dr.zeros(mi.SurfaceInteraction3f, len(out))
    si.uv = mi.Point2f(u.astype(np.float32), v.astype(np.float32))
    si.wi = mi.Vector3f(wo.T)
    value = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(wi.T))
    check_radiance(np.array(value).T, out)
    # Below either horizon: zero.
    flip = mi.Vector3f(wi[:, 0], wi[:, 1], -wi[:, 2])
    assert np.all(np.array(bsdf.eval(mi.BSDFContext(), si, flip)) == 0)


@needs_fixture
def test_llvm_pixel_mode_matches_flashmat_row():
    mi = set_variant("llvm_ad_rgb")
    pix, params, wi, wo, out = load_rows()
    i, j = int(pix[0, 0]), int(pix[0, 1])
    bsdf = mi.load_dict({"type": "neural_brdf", "filename": str(TINY_NMAT), "pixel_x": j, "pixel_y": i})
    got = np.array(bsdf.log_radiance(None, mi.Vector3f(wi.T), mi.Vector3f(wo.T))).T
    np.testing.assert_allclose(got[0], out[0], rtol=RTOL, atol=RTOL)
    # All rows' directions with pixel (i, j)'s parameters, against the numpy reference.
    nm = read_nmat(TINY_NMAT)
    ref = reference_log_radiance(nm, np.repeat(nm.neural_map[:, i, j][None], len(wi), 0), wi, wo)
    np.testing.assert_allclose(got, ref, rtol=RTOL, atol=RTOL)


@needs_fixture
def test_llvm_sample_weight_is_eval_over_pdf():
    mi = set_variant("llvm_ad_rgb")
    import drjit as dr

    n = 4096
    rng = np.random.default_rng(3)
    bsdf = mi.load_dict({"type": "neural_brdf", "filename": str(TINY_NMAT), "mode": "texture"})
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.uv = mi.Point2f(rng.random(n).astype(np.float32), rng.random(n).astype(np.float32))
    wi = rng.standard_normal((n, 3))
    wi[:, 2] = np.abs(wi[:, 2]) + 0.05
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    si.wi = mi.Vector3f(wi.T.astype(np.float32))
    ctx = mi.BSDFContext()
    s2 = mi.Point2f(rng.random((2, n)).astype(np.float32))
    bs, weight = bsdf.sample(ctx, si, mi.Float(rng.random(n).astype(np.float32)), s2)
    value, pdf = bsdf.eval_pdf(ctx, si, bs.wo)
    weight, value, pdf = np.array(weight).T, np.array(value).T, np.array(pdf)
    np.testing.assert_allclose(np.array(bs.pdf), pdf, rtol=1e-5)
    np.testing.assert_allclose(pdf, np.maximum(np.array(bs.wo)[2], 0) / math.pi, rtol=1e-5, atol=1e-7)
    ok = pdf > 1e-4
    assert ok.mean() > 0.95
    np.testing.assert_allclose(weight[ok], value[ok] / pdf[ok, None], rtol=1e-4, atol=1e-6)
    assert np.any(value > 0)


def test_llvm_chi2_sample_matches_pdf(synthetic_nmat):
    mi = set_variant("llvm_ad_rgb")
    from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain

    extra = f'<string name="filename" value="{synthetic_nmat}"/>'
    # Each incident direction is a kernel constant: one ~20 s LLVM compile each (first run).
    for wi in ([0, 0, 1], [-0.3, 0.9, 0.3162278]):
        sample_func, pdf_func = BSDFAdapter("neural_brdf", extra, wi=wi)
        chi2 = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func, sample_dim=3)
        assert chi2.run(), chi2.messages


def test_scalar_bilinear_and_normal(synthetic_nmat):
    mi = set_variant("scalar_rgb")
    nm = read_nmat(synthetic_nmat)
    c, h, w = nm.neural_map.shape
    ctx = mi.BSDFContext()
    near = mi.load_dict({"type": "neural_brdf", "filename": str(synthetic_nmat), "mode": "texture"})
    bil = mi.load_dict(
        {"type": "neural_brdf", "filename": str(synthetic_nmat), "mode": "texture", "filter": "bilinear"}
    )
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(0.3, -0.2, 0.9327379)
    wo = mi.Vector3f(-0.5, 0.1, 0.8602325)
    # At a pixel centre, bilinear == nearest == pixel mode.
    si.uv = mi.Point2f((2 + 0.5) / w, 1 - (5 + 0.5) / h)
    pix = mi.load_dict({"type": "neural_brdf", "filename": str(synthetic_nmat), "pixel_x": 2, "pixel_y": 5})
    a, b, p = (np.array(x.eval(ctx, si, wo)) for x in (near, bil, pix))
    np.testing.assert_allclose(a, p, rtol=1e-6)
    np.testing.assert_allclose(b, p, rtol=1e-5)
    assert np.all(p > 0)
    # Half way between two columns: the parameters are averaged.
    si.uv = mi.Point2f(3.0 / w, 1 - (5 + 0.5) / h)
    mid = 0.5 * (nm.neural_map[:, 5, 2] + nm.neural_map[:, 5, 3]).astype(np.float64)
    ref = reference_log_radiance(nm, mid[None], [list(wo)], [list(si.wi)])[0]
    np.testing.assert_allclose(np.array(bil.eval(ctx, si, wo)) * math.pi, np.maximum(np.expm1(ref), 0), rtol=1e-5)
    # Normal correction: the network sees R d, R = [u v n], u = normalize(x - (x.n) n), v = n x u.
    n = np.array([0.2, -0.1, 1.0])
    n /= np.linalg.norm(n)
    nb = mi.load_dict(
        {"type": "neural_brdf", "filename": str(synthetic_nmat), "pixel_x": 2, "pixel_y": 5,
         "normal": mi.ScalarVector3f(*n)}
    )
    rot = correction_matrix(n)
    ref = reference_log_radiance(
        nm, nm.neural_map[:, 5, 2][None].astype(np.float64), [rot @ np.array(wo)], [rot @ np.array(si.wi)]
    )[0]
    # Loose: the rotation is f32 in the plugin, f64 here, and the top encoding frequency
    # (2^15 pi) turns last-bit differences of the directions into ~1e-3 of output.
    got = np.array(nb.eval(ctx, si, wo)) * math.pi
    np.testing.assert_allclose(got, np.maximum(np.expm1(ref), 0), rtol=5e-3)
    assert np.abs(got - p * math.pi).max() > 1e-2  # the normal changes the value
    # Pixel outside the map: a clear error.
    with pytest.raises(Exception, match="outside"):
        mi.load_dict({"type": "neural_brdf", "filename": str(synthetic_nmat), "pixel_x": w, "pixel_y": 0})


@needs_fixture
def test_llvm_render_matches_identity_reference():
    """A whole Mitsuba render (direct illumination, point light at the camera,
    the rectangle filling a 28 degree view) equals the numpy reference's
    identity render (flashmat relight --identity) divided by pi r^2: checks the
    UV orientation (row 0 at the top), the pi convention and the light/camera
    direction roles inside Mitsuba's integrator."""
    mi = set_variant("llvm_ad_rgb")
    nm = read_nmat(TINY_NMAT)
    c, h, w = nm.neural_map.shape
    d = 1.0 / math.tan(math.radians(14.0))
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
        "sensor": {
            "type": "perspective", "fov": 28, "fov_axis": "x",
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, d], target=[0, 0, 0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": w, "height": h, "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": 16},
        },
        "light": {"type": "point", "position": [0, 0, d], "intensity": {"type": "rgb", "value": 1.0}},
        "rect": {"type": "rectangle", "bsdf": {"type": "neural_brdf", "filename": str(TINY_NMAT), "mode": "texture"}},
    })
    img = np.array(mi.render(scene), dtype=np.float64)  # [H, W, 3]
    xs = 2 * (np.arange(w) + 0.5) / w - 1
    ys = 1 - 2 * (np.arange(h) + 0.5) / h
    pos = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], np.zeros((h, w))), -1).reshape(-1, 3)
    dirs = np.array([0, 0, d]) - pos
    r2 = (dirs**2).sum(-1)
    dirs = dirs / np.sqrt(r2)[:, None]
    out = reference_log_radiance(nm, nm.neural_map.reshape(c, -1).T.astype(np.float64), dirs, dirs)
    expected = (np.maximum(np.expm1(out), 0) / (math.pi * r2[:, None])).reshape(h, w, 3)
    # Sub-pixel jitter moves the directions a little: compare medians, not every pixel.
    log_diff = np.abs(np.log1p(img) - np.log1p(expected))
    assert np.median(log_diff) < 1e-3, np.median(log_diff)
    assert np.corrcoef(np.log1p(img).ravel(), np.log1p(expected).ravel())[0, 1] > 0.999


def test_scalar_gain_scales_eval(synthetic_nmat, tmp_path):
    """A material's exposure gain multiplies eval, each channel by its own (and only eval: the network's log radiance
    is the same)."""
    from conftest import write_nmat, synthetic_tensors

    mi = set_variant("scalar_rgb")
    t, meta = synthetic_tensors()
    values = {}
    for gain in ("1", "0.25", "[0.5, 2, 0.125]"):
        p = tmp_path / f"gain{len(values)}.nmat"
        write_nmat(p, t, {**meta, "flashmat.version": "4", "gain": gain})
        bsdf = mi.load_dict({"type": "neural_brdf", "filename": str(p), "pixel_x": 3, "pixel_y": 2})
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(0.3, -0.2, 0.93)
        values[gain] = np.array(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(-0.1, 0.4, 0.91)))
    assert values["1"].max() > 0
    np.testing.assert_allclose(values["0.25"], 0.25 * values["1"], rtol=1e-6)
    np.testing.assert_allclose(values["[0.5, 2, 0.125]"], np.array([0.5, 2, 0.125]) * values["1"], rtol=1e-6)
