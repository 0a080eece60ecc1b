"""Normal correction (docs/MITSUBA.md) and the two network implementations."""
import math

import numpy as np
import pytest

from conftest import TINY_NMAT, set_variant
from flashmat.mitsuba.bsdf import correction_matrix
from flashmat.mitsuba.ggx import ggx_radiance
from flashmat.mitsuba.nmat import read_nmat, reference_log_radiance


def unit(v):
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def random_dirs(rng, m):
    d = rng.standard_normal((m, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.1
    return unit(d)


def test_correction_matrix_is_identity_for_the_macro_normal():
    r = correction_matrix([0.0, 0.0, 1.0])
    assert np.array_equal(r, np.eye(3))  # exactly: M_render's training frame is left alone
    # REFERENCE section 7's literal u = normalize(n x (1,0,0)) would give a 90 degree turn here:
    u = np.cross([0.0, 0.0, 1.0], [1.0, 0.0, 0.0])
    assert np.allclose(u, [0, 1, 0])


def test_correction_matrix_rotates_z_to_n():
    rng = np.random.default_rng(1)
    for n in random_dirs(rng, 20):
        r = correction_matrix(n)
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) > 0.999
        np.testing.assert_allclose(r @ [0, 0, 1], n, atol=1e-12)
        # u is the x axis made orthogonal to n (Gram-Schmidt): in the plane of x and n.
        assert abs(np.dot(r[:, 0], np.cross([1.0, 0, 0], n))) < 1e-12


def test_correction_cancels_an_encoded_normal():
    """A BRDF whose normal is n (flashmat's GGX with the pixel's normal), fed
    R d, behaves like the same BRDF with the macro normal z fed d: the correction
    removes the encoded normal. The opposite rotation (R^T) does not."""
    rng = np.random.default_rng(2)
    m = 500
    kd, ks, r = np.tile([0.3, 0.2, 0.1], (m, 1)), np.tile([0.3, 0.3, 0.3], (m, 1)), np.full(m, 0.3)
    n = unit([0.3, -0.2, 1.0])
    rot = correction_matrix(n)
    wi, wo = random_dirs(rng, m), random_dirs(rng, m)
    flat = ggx_radiance(kd, ks, r, np.tile([0, 0, 1.0], (m, 1)), wi, wo)
    corrected = ggx_radiance(kd, ks, r, np.tile(n, (m, 1)), wi @ rot.T, wo @ rot.T)
    ok = (wi @ rot.T)[:, 2] > 0.05
    ok &= (wo @ rot.T)[:, 2] > 0.05
    np.testing.assert_allclose(corrected[ok], flat[ok], rtol=1e-9)
    wrong = ggx_radiance(kd, ks, r, np.tile(n, (m, 1)), wi @ rot, wo @ rot)
    assert np.abs(wrong[ok] - flat[ok]).max() > 0.05


@pytest.mark.skipif(not TINY_NMAT.exists(), reason="fixture missing")
def test_llvm_normal_correction():
    mi = set_variant("llvm_ad_rgb")
    import drjit as dr

    nm = read_nmat(TINY_NMAT)
    i, j = 7, 11
    rng = np.random.default_rng(3)
    m = 256
    wi, wo = random_dirs(rng, m).astype(np.float32), random_dirs(rng, m).astype(np.float32)
    si = dr.zeros(mi.SurfaceInteraction3f, m)
    si.wi = mi.Vector3f(wo.T)
    ctx = mi.BSDFContext()
    base = {"type": "neural_brdf", "filename": str(TINY_NMAT), "pixel_x": j, "pixel_y": i}
    plain = np.array(mi.load_dict(base).eval(ctx, si, mi.Vector3f(wi.T)))
    # n = +z: bit-identical to no correction.
    z = mi.load_dict(dict(base, normal=mi.ScalarVector3f(0, 0, 1)))
    assert np.array_equal(np.array(z.eval(ctx, si, mi.Vector3f(wi.T))), plain)
    # The network is not symmetric under a 90 degree turn about z, so the
    # literal REFERENCE frame would change every pixel's appearance.
    p = nm.neural_map[:, i, j][None].astype(np.float64).repeat(m, 0)
    turn = np.array([[0, 1, 0], [-1, 0, 0], [0, 0, 1.0]])  # d -> (d.y, -d.x, d.z)
    a = reference_log_radiance(nm, p, wi, wo)
    b = reference_log_radiance(nm, p, wi @ turn.T, wo @ turn.T)
    assert np.abs(a - b).max() > 1e-2
    # A tilted normal: the network sees R d.
    n = unit([-0.2, 0.15, 1.0])
    rot = correction_matrix(n)
    tilted = mi.load_dict(dict(base, normal=mi.ScalarVector3f(*n)))
    got = np.array(tilted.eval(ctx, si, mi.Vector3f(wi.T))).T * math.pi
    ref = np.maximum(np.expm1(reference_log_radiance(nm, p, wi @ rot.T, wo @ rot.T)), 0)
    # The rotated directions differ from the f64 ones in the last f32 bits, which the
    # top encoding frequency (2^15 pi) amplifies: compare robustly.
    rel = np.abs(got - ref) / (np.abs(ref) + 1e-3)
    assert np.median(rel) < 5e-3, np.median(rel)
    assert np.corrcoef(got.ravel(), ref.ravel())[0, 1] > 0.99
    assert np.abs(got - plain.T * math.pi).max() > 1e-2


@pytest.mark.skipif(not TINY_NMAT.exists(), reason="fixture missing")
def test_unrolled_and_coopvec_networks_agree():
    mi = set_variant("llvm_ad_rgb")
    import drjit as dr

    from flashmat.mitsuba.network import coopvec_available

    if not coopvec_available():
        pytest.skip("this Dr.Jit has no drjit.nn")
    rng = np.random.default_rng(4)
    m = 512
    si = dr.zeros(mi.SurfaceInteraction3f, m)
    si.uv = mi.Point2f(rng.random((2, m)).astype(np.float32))
    si.wi = mi.Vector3f(random_dirs(rng, m).T.astype(np.float32))
    wo = mi.Vector3f(random_dirs(rng, m).T.astype(np.float32))
    vals = {}
    for net in ("coopvec", "unrolled"):
        bsdf = mi.load_dict({"type": "neural_brdf", "filename": str(TINY_NMAT), "mode": "texture", "network": net})
        assert f"network={'CoopVecNetwork' if net == 'coopvec' else 'UnrolledNetwork'}" in str(bsdf)
        vals[net] = np.array(bsdf.eval(mi.BSDFContext(), si, wo))
    assert np.mean(vals["coopvec"] > 0) > 0.3
    np.testing.assert_allclose(vals["coopvec"], vals["unrolled"], rtol=1e-4, atol=1e-6)
    with pytest.raises(Exception, match="network must be one of"):
        mi.load_dict({"type": "neural_brdf", "filename": str(TINY_NMAT), "network": "fast"})


@pytest.mark.skipif(not TINY_NMAT.exists(), reason="fixture missing")
def test_llvm_texture_normals(tmp_path):
    """Texture mode with a normals file: +z everywhere changes nothing; a tilted
    pixel normal gives that pixel's pixel-mode value with `normal` set."""
    mi = set_variant("llvm_ad_rgb")
    import drjit as dr

    nm = read_nmat(TINY_NMAT)
    h, w = nm.resolution
    rng = np.random.default_rng(6)
    m = 64
    ii, jj = rng.integers(0, h, m), rng.integers(0, w, m)
    wi, wo = random_dirs(rng, m).astype(np.float32), random_dirs(rng, m).astype(np.float32)
    si = dr.zeros(mi.SurfaceInteraction3f, m)
    si.uv = mi.Point2f(((jj + 0.5) / w).astype(np.float32), (1 - (ii + 0.5) / h).astype(np.float32))
    si.wi = mi.Vector3f(wo.T)
    ctx = mi.BSDFContext()
    flat = np.zeros((h, w, 3))
    flat[..., 2] = 1.0
    np.save(tmp_path / "flat.npy", flat)
    tilted = unit(np.stack([0.3 * np.sin(np.arange(h))[:, None].repeat(w, 1),
                            0.2 * np.cos(np.arange(w))[None, :].repeat(h, 0), np.ones((h, w))], -1))
    np.save(tmp_path / "tilted.npy", tilted.transpose(2, 0, 1))  # [3, H, W] is accepted too
    base = {"type": "neural_brdf", "filename": str(TINY_NMAT), "mode": "texture"}
    plain = np.array(mi.load_dict(base).eval(ctx, si, mi.Vector3f(wi.T)))
    same = np.array(mi.load_dict(dict(base, normals=str(tmp_path / "flat.npy"))).eval(ctx, si, mi.Vector3f(wi.T)))
    assert np.array_equal(same, plain)
    got = np.array(mi.load_dict(dict(base, normals=str(tmp_path / "tilted.npy"))).eval(ctx, si, mi.Vector3f(wi.T))).T
    for k in range(0, m, 16):
        px = mi.load_dict({"type": "neural_brdf", "filename": str(TINY_NMAT), "pixel_x": int(jj[k]),
                           "pixel_y": int(ii[k]), "normal": mi.ScalarVector3f(*tilted[ii[k], jj[k]])})
        s1 = dr.zeros(mi.SurfaceInteraction3f, 1)
        s1.wi = mi.Vector3f(*[float(x) for x in wo[k]])
        one = np.array(px.eval(ctx, s1, mi.Vector3f(*[float(x) for x in wi[k]]))).ravel()
        np.testing.assert_allclose(got[k], one, rtol=1e-4, atol=1e-7)
    assert np.abs(got - plain.T).max() > 1e-3
    # Bad normals: one clear error.
    np.save(tmp_path / "down.npy", -flat)
    with pytest.raises(Exception, match="z > 0"):
        mi.load_dict(dict(base, normals=str(tmp_path / "down.npy")))
    with pytest.raises(Exception, match="z > 0"):
        mi.load_dict({"type": "neural_brdf", "filename": str(TINY_NMAT), "normal": mi.ScalarVector3f(0, 0, -1)})
