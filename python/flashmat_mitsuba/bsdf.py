"""The `neural_brdf` Mitsuba 3 BSDF: a flashmat neural material (.nmat).

Scene description (XML or ``mi.load_dict``)::

    <bsdf type="neural_brdf">
        <string name="filename" value="material.nmat"/>
        <string name="mode" value="texture"/>      <!-- or "pixel" (default) -->
        <string name="filter" value="nearest"/>    <!-- texture mode: or "bilinear" -->
        <integer name="pixel_x" value="10"/>       <!-- pixel mode: column -->
        <integer name="pixel_y" value="20"/>       <!-- pixel mode: row (0 = top) -->
        <vector name="normal" value="0, 0.1, 1"/>  <!-- optional, pixel mode -->
        <string name="normals" value="n.npy"/>     <!-- optional, texture mode: [H, W, 3] or [3, H, W] -->
    </bsdf>

Math (docs/NMAT.md): with wi the direction towards the light and wo towards
the camera (Mitsuba's sampled/queried ``wo`` and ``si.wi`` respectively),
out = M_render(params, ND_enc(wi, wo)) = ln(1 + R), R = exp(out) - 1
includes the cosine and a factor pi, so the BRDF is f = R / (pi cos(wi)) and
``eval`` (f times the cosine) returns R / pi. Zero below either horizon.
Sampling is cosine-weighted over the hemisphere.

The networks are evaluated with Dr.Jit arrays as unrolled fused
multiply-adds over the weight matrices (weights become kernel constants), so
one traced kernel evaluates every lane; fine for the `tiny` and `compact`
presets, heavy to trace for `paper` (about 0.6 M operations per evaluation).
"""
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from .nmat import read_nmat, reference_log_radiance

INV_PI = 1.0 / math.pi
MAX_LOG_RADIANCE = 80.0


def _leaky(x, slope):
    return dr.maximum(x, x * slope)


def _matvec(w, x, slope=None, bias=None):
    """w: numpy [out, in]; x: list of `in` Floats -> list of `out` Floats."""
    out = []
    rows, cols = w.shape
    for r in range(rows):
        row = w[r]
        acc = x[0] * float(row[0]) if bias is None else dr.fma(x[0], float(row[0]), bias[r])
        for j in range(1, cols):
            acc = dr.fma(x[j], float(row[j]), acc)
        out.append(acc if slope is None else _leaky(acc, slope))
    return out


def _resolve(path):
    fr = mi.file_resolver() if hasattr(mi, "file_resolver") else mi.Thread.thread().file_resolver()
    return str(fr.resolve(path))


def _floor_mod2(x):
    # (2^k v) mod 2, exact in floating point (docs/NMAT.md, encoding step 3).
    return x - 2.0 * dr.floor(x * 0.5)


_CLASSES = {}


def neural_brdf_class():
    """The NeuralBRDF class for the current Mitsuba variant (mi.BSDF differs per variant)."""
    variant = mi.variant()
    if variant is None:
        raise RuntimeError("flashmat_mitsuba: set a Mitsuba variant (mi.set_variant) first")
    if variant in _CLASSES:
        return _CLASSES[variant]

    class NeuralBRDF(mi.BSDF):
        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            if "spectral" in mi.variant() or "mono" in mi.variant():
                raise ValueError(f"neural_brdf renders RGB: use an *_rgb variant, not {mi.variant()}")
            filename = str(props.get("filename", ""))
            if not filename:
                raise ValueError("neural_brdf: the `filename` property (a .nmat file) is required")
            resolved = _resolve(filename)
            self.nmat = read_nmat(resolved)
            self.filename = resolved
            self.mode = str(props.get("mode", "pixel"))
            self.filter = str(props.get("filter", "nearest"))
            if self.mode not in ("pixel", "texture"):
                raise ValueError(f"neural_brdf ({filename}): mode must be 'pixel' or 'texture', got {self.mode!r}")
            if self.filter not in ("nearest", "bilinear"):
                raise ValueError(f"neural_brdf ({filename}): filter must be 'nearest' or 'bilinear', got {self.filter!r}")
            c, h, w = self.nmat.neural_map.shape
            self.C, self.H, self.W = c, h, w
            self.jit = dr.is_jit_v(mi.Float)
            m0 = self.nmat.m_render[0].astype(np.float64)
            self.m0_params, self.m0_code = m0[:, :c], np.ascontiguousarray(m0[:, c:])

            self.normal = None
            self.normals = None
            if self.mode == "pixel":
                self.pixel_x = int(props.get("pixel_x", w // 2))
                self.pixel_y = int(props.get("pixel_y", h // 2))
                if not (0 <= self.pixel_x < w and 0 <= self.pixel_y < h):
                    raise ValueError(
                        f"neural_brdf ({filename}): pixel ({self.pixel_x}, {self.pixel_y}) outside the {w}x{h} map"
                    )
                p = self.nmat.neural_map[:, self.pixel_y, self.pixel_x].astype(np.float64)
                # The parameters are constant: fold M0's parameter columns into a bias.
                self.bias0 = [float(b) for b in self.m0_params @ p]
                if "normal" in props:
                    n = np.array(list(props["normal"]), dtype=np.float64)
                    self.normal = n / np.linalg.norm(n)
            else:
                flat = np.ascontiguousarray(self.nmat.neural_map, dtype=np.float32).reshape(-1)
                self.map_np = self.nmat.neural_map.astype(np.float64)
                self.map_buf = mi.Float(flat) if self.jit else None
                if "normals" in props:
                    n = np.load(_resolve(str(props["normals"]))).astype(np.float64)
                    if n.shape == (3, h, w):
                        n = n.transpose(1, 2, 0)
                    if n.shape != (h, w, 3):
                        raise ValueError(f"neural_brdf ({filename}): normals must be [{h}, {w}, 3] or [3, {h}, {w}], got {n.shape}")
                    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
                    self.normals = n
                    self.normals_buf = mi.Float(n.reshape(-1).astype(np.float32)) if self.jit else None

            flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
            self.m_components = [flags]
            self.m_flags = flags

        # ------------------------------------------------------------ lookups
        def _pixel_index(self, uv):
            """Nearest pixel (row, column) of a UV: u -> column, v -> row, row 0 at the top (v = 1)."""
            w, h = self.W, self.H
            j = dr.clip(mi.Int32(dr.floor(uv.x * w)), 0, w - 1)
            i = dr.clip(mi.Int32(dr.floor((1.0 - uv.y) * h)), 0, h - 1)
            return i, j

        def _gather_map(self, i, j, active):
            """The C parameters of pixel (i, j) as a list of Floats."""
            if not self.jit:
                return [float(x) for x in self.map_np[:, int(i), int(j)]]
            idx = mi.UInt32(i * self.W + j)
            hw = self.H * self.W
            return [dr.gather(mi.Float, self.map_buf, idx + ch * hw, active) for ch in range(self.C)]

        def _params(self, si, active):
            uv = si.uv
            if self.filter == "nearest":
                i, j = self._pixel_index(uv)
                return self._gather_map(i, j, active)
            # Bilinear between pixel centres (column j = u W - 0.5, row i = (1 - v) H - 0.5), clamped at the edges.
            x = uv.x * self.W - 0.5
            y = (1.0 - uv.y) * self.H - 0.5
            x0f, y0f = dr.floor(x), dr.floor(y)
            fx, fy = x - x0f, y - y0f
            x0 = mi.Int32(x0f)
            y0 = mi.Int32(y0f)
            cx = lambda t: dr.clip(t, 0, self.W - 1)
            cy = lambda t: dr.clip(t, 0, self.H - 1)
            corners = [
                (cy(y0), cx(x0), (1.0 - fx) * (1.0 - fy)),
                (cy(y0), cx(x0 + 1), fx * (1.0 - fy)),
                (cy(y0 + 1), cx(x0), (1.0 - fx) * fy),
                (cy(y0 + 1), cx(x0 + 1), fx * fy),
            ]
            out = None
            for i, j, wgt in corners:
                p = self._gather_map(i, j, active)
                out = [q * wgt for q in p] if out is None else [dr.fma(q, wgt, o) for q, o in zip(p, out)]
            return out

        def _normal(self, si, active):
            if self.mode == "pixel":
                return None if self.normal is None else mi.Vector3f(*[float(t) for t in self.normal])
            if self.normals is None:
                return None
            i, j = self._pixel_index(si.uv)
            if not self.jit:
                return mi.Vector3f(*[float(t) for t in self.normals[int(i), int(j)]])
            idx = mi.UInt32(i * self.W + j) * 3
            return mi.Vector3f(*[dr.gather(mi.Float, self.normals_buf, idx + k, active) for k in range(3)])

        # ------------------------------------------------------------ network
        def log_radiance(self, params, wi, wo):
            """M_render output ln(1 + R) (Color3f) for a light direction wi and a
            view direction wo in the material frame. params: list of C Floats, or
            None in pixel mode (the pixel's parameters, folded into a bias)."""
            if not self.jit:
                # scalar variants: numpy, one row (the half vector rounded like flashmat's f32).
                p = self.nmat.neural_map[:, self.pixel_y, self.pixel_x] if params is None else params
                out = reference_log_radiance(
                    self.nmat, np.asarray(p, np.float64)[None], [[wi.x, wi.y, wi.z]], [[wo.x, wo.y, wo.z]]
                )[0]
                return mi.Color3f(*[float(t) for t in out])
            # The half vector, rounded like flashmat's f32 (no FMA, division): see half_vector_f32.
            s = wi + wo
            n2 = (s.x * s.x + s.y * s.y) + s.z * s.z
            norm = dr.maximum(dr.sqrt(n2), 1e-12)
            # Per component: Vector3f / Float would multiply by a rounded reciprocal.
            h = mi.Vector3f(s.x / norm, s.y / norm, s.z / norm)
            v = [wi.x, wi.y, wi.z, wo.x, wo.y, wo.z, h.x, h.y, h.z]
            sins, coss = [], []
            for k in range(self.nmat.frequencies):
                for c in range(9):
                    phase = math.pi * _floor_mod2(v[c] * float(2.0**k))
                    s, co = dr.sincos(phase)
                    sins.append(s)
                    coss.append(co)
            e = v + sins + coss
            enc = self.nmat.nd_enc
            a = _matvec(enc[0], e, 0.01)
            b = _matvec(enc[1], a, 0.01)
            code = _matvec(enc[2], b)
            if params is None:
                y = _matvec(self.m0_code, code, bias=self.bias0)
            else:
                y = _matvec(self.nmat.m_render[0], list(params) + code)
            for n in range(1, 6):
                y = _matvec(self.nmat.m_render[n], y, 0.01)
            out = _matvec(self.nmat.m_render[6], y, 0.001)
            return mi.Color3f(*out)

        def _value(self, si, wo, active):
            """(eval value R / pi, valid mask) for Mitsuba's si.wi (camera) and wo (light), local frame."""
            cam, light = si.wi, wo
            active = active & (mi.Frame3f.cos_theta(cam) > 0) & (mi.Frame3f.cos_theta(light) > 0)
            n = self._normal(si, active)
            if n is not None:
                # REFERENCE section 7: u = normalize(n x (1,0,0)), v = n x u, R = [u v n].
                u = dr.normalize(dr.cross(n, mi.Vector3f(1.0, 0.0, 0.0)))
                vv = dr.cross(n, u)
                to = lambda d: mi.Vector3f(dr.dot(d, u), dr.dot(d, vv), dr.dot(d, n))
                cam, light = to(cam), to(light)
            params = None if self.mode == "pixel" else self._params(si, active)
            out = self.log_radiance(params, light, cam)
            r = dr.maximum(dr.exp(dr.minimum(out, MAX_LOG_RADIANCE)) - 1.0, 0.0)
            return dr.select(active, r * INV_PI, 0.0), active

        # ------------------------------------------------------------ BSDF API
        def _enabled(self, ctx):
            return ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0)

        def eval(self, ctx, si, wo, active=True):
            if not self._enabled(ctx):
                return mi.Color3f(0.0)
            value, _ = self._value(si, wo, active)
            return value

        def pdf(self, ctx, si, wo, active=True):
            if not self._enabled(ctx):
                return mi.Float(0.0)
            ok = active & (mi.Frame3f.cos_theta(si.wi) > 0) & (mi.Frame3f.cos_theta(wo) > 0)
            return dr.select(ok, mi.warp.square_to_cosine_hemisphere_pdf(wo), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            bs = dr.zeros(mi.BSDFSample3f)
            if not self._enabled(ctx):
                return bs, mi.Color3f(0.0)
            active = active & (mi.Frame3f.cos_theta(si.wi) > 0)
            bs.wo = mi.warp.square_to_cosine_hemisphere(sample2)
            bs.pdf = dr.select(active, mi.warp.square_to_cosine_hemisphere_pdf(bs.wo), 0.0)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            bs.sampled_component = mi.UInt32(0)
            value, ok = self._value(si, bs.wo, active)
            ok = ok & (bs.pdf > 0)
            weight = dr.select(ok, value / dr.select(ok, bs.pdf, 1.0), 0.0)
            return bs, weight

        def traverse(self, callback):
            pass

        def parameters_changed(self, keys):
            pass

        def to_string(self):
            extra = f"pixel=({self.pixel_x}, {self.pixel_y})" if self.mode == "pixel" else f"filter={self.filter}"
            return (
                f"NeuralBRDF[filename={self.filename!r}, model_id={self.nmat.meta.get('model_id')!r}, "
                f"map={self.C}x{self.H}x{self.W}, mode={self.mode}, {extra}]"
            )

    _CLASSES[variant] = NeuralBRDF
    return NeuralBRDF


def NeuralBRDF(props):
    """A neural_brdf BSDF of the current variant from Mitsuba properties."""
    return neural_brdf_class()(props)


def register():
    """Registers `neural_brdf` for the current Mitsuba variant (call after mi.set_variant)."""
    cls = neural_brdf_class()
    mi.register_bsdf("neural_brdf", lambda props: cls(props))
