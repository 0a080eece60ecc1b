"""ND_enc + M_render (docs/NMAT.md, "Rendering one pixel") as Dr.Jit programs.

Two implementations of the same math, both vectorised over the lanes of a
JIT variant (llvm_*, cuda_*):

- :class:`CoopVecNetwork` (default): Dr.Jit cooperative vectors
  (``drjit.nn``, Dr.Jit >= 1.1). Each layer is one ``drjit.nn.matvec`` whose
  weights live in a packed buffer, so the traced kernel is small and does not
  depend on the weight values: one compile per network *size*, shared by
  every material, pixel and scene (and cached on disk by Dr.Jit).
- :class:`UnrolledNetwork`: every multiply-add is a separate Dr.Jit
  operation with the weight as a literal. The kernel grows with the weight
  count (~0.1 M operations for `compact`, ~0.6 M for `paper`) and must be
  recompiled for every material or pixel; kept as a fallback for Dr.Jit
  builds without ``drjit.nn`` and as a cross-check in the tests.

Both take the pixel parameters (a list of C Floats) or, for a constant pixel
(``pixel`` mode), fold M0's parameter columns into a bias computed once in
float64.
"""
import math

import drjit as dr
import numpy as np

try:  # Dr.Jit >= 1.1
    import drjit.nn as _nn
except ImportError:  # pragma: no cover - depends on the installed Dr.Jit
    _nn = None


def coopvec_available():
    return _nn is not None


def _leaky(x, slope):
    return dr.maximum(x, x * slope)


def _floor_mod2(x):
    # (2^k v) mod 2, exact in floating point (docs/NMAT.md, encoding step 3).
    return x - 2.0 * dr.floor(x * 0.5)


def half_vector(wi, wo, vector_type):
    """normalize(wi + wo) rounded like flashmat's f32 (see nmat.half_vector_f32)."""
    s = wi + wo
    n2 = (s.x * s.x + s.y * s.y) + s.z * s.z
    norm = dr.maximum(dr.sqrt(n2), 1e-12)
    # Per component: Vector3f / Float would multiply by a rounded reciprocal.
    return vector_type(s.x / norm, s.y / norm, s.z / norm)


def encode_directions(wi, wo, frequencies, vector_type):
    """The 9 + 18 F inputs of ND_enc: [wi, wo, h, sin(2^k pi v_c), cos(2^k pi v_c)], k-major."""
    h = half_vector(wi, wo, vector_type)
    v = [wi.x, wi.y, wi.z, wo.x, wo.y, wo.z, h.x, h.y, h.z]
    sins, coss = [], []
    for k in range(frequencies):
        scale = float(2.0**k)
        for c in range(9):
            s, co = dr.sincos(math.pi * _floor_mod2(v[c] * scale))
            sins.append(s)
            coss.append(co)
    return v + sins + coss


def pixel_bias(nmat, params):
    """M0's parameter columns times a constant pixel's parameters (float64)."""
    c = nmat.channels
    return nmat.m_render[0][:, :c].astype(np.float64) @ np.asarray(params, np.float64)


class CoopVecNetwork:
    """ND_enc + M_render with drjit.nn cooperative vectors (one matvec per layer)."""

    def __init__(self, nmat, tensor_type, float_type, pixel_params=None):
        self.nmat = nmat
        self.float_type = float_type
        c = nmat.channels
        m0 = nmat.m_render[0]
        mats = [tensor_type(np.ascontiguousarray(w, np.float32)) for w in nmat.nd_enc]
        self.constant_pixel = pixel_params is not None
        if self.constant_pixel:
            mats.append(tensor_type(np.ascontiguousarray(m0[:, c:], np.float32)))
            mats.append(float_type(pixel_bias(nmat, pixel_params).astype(np.float32)))
        else:
            mats.append(tensor_type(np.ascontiguousarray(m0, np.float32)))
        mats += [tensor_type(np.ascontiguousarray(w, np.float32)) for w in nmat.m_render[1:]]
        # One packed buffer in the inference-optimal layout.
        views = _nn.pack(*mats, layout="inference")
        self.enc = views[:3]
        if self.constant_pixel:
            self.m0, self.bias0 = views[3], views[4]
            self.rest = views[5:]
        else:
            self.m0, self.bias0 = views[3], None
            self.rest = views[4:]

    def __call__(self, params, wi, wo, vector_type):
        e = encode_directions(wi, wo, self.nmat.frequencies, vector_type)
        x = _nn.CoopVec(*e)
        x = _leaky(_nn.matvec(self.enc[0], x), 0.01)
        x = _leaky(_nn.matvec(self.enc[1], x), 0.01)
        code = _nn.matvec(self.enc[2], x)
        if self.constant_pixel:
            y = _nn.matvec(self.m0, code, self.bias0)
        else:
            y = _nn.matvec(self.m0, _nn.CoopVec(*params, *list(code)))
        for w in self.rest[:-1]:
            y = _leaky(_nn.matvec(w, y), 0.01)
        out = _leaky(_nn.matvec(self.rest[-1], y), 0.001)
        return list(out)


def _matvec(w, x, slope=None, bias=None):
    """w: numpy [out, in]; x: list of `in` Floats -> list of `out` Floats (unrolled fma)."""
    out = []
    rows, cols = w.shape
    for r in range(rows):
        row = w[r]
        acc = x[0] * float(row[0]) if bias is None else dr.fma(x[0], float(row[0]), bias[r])
        for j in range(1, cols):
            acc = dr.fma(x[j], float(row[j]), acc)
        out.append(acc if slope is None else _leaky(acc, slope))
    return out


class UnrolledNetwork:
    """ND_enc + M_render unrolled into scalar fused multiply-adds (weights as literals)."""

    def __init__(self, nmat, pixel_params=None):
        self.nmat = nmat
        c = nmat.channels
        self.m0_code = np.ascontiguousarray(nmat.m_render[0][:, c:].astype(np.float64))
        self.bias0 = None if pixel_params is None else [float(b) for b in pixel_bias(nmat, pixel_params)]

    def __call__(self, params, wi, wo, vector_type):
        e = encode_directions(wi, wo, self.nmat.frequencies, vector_type)
        enc = self.nmat.nd_enc
        a = _matvec(enc[0], e, 0.01)
        b = _matvec(enc[1], a, 0.01)
        code = _matvec(enc[2], b)
        if self.bias0 is not None:
            y = _matvec(self.m0_code, code, bias=self.bias0)
        else:
            y = _matvec(self.nmat.m_render[0], list(params) + code)
        for n in range(1, 6):
            y = _matvec(self.nmat.m_render[n], y, 0.01)
        return _matvec(self.nmat.m_render[6], y, 0.001)
