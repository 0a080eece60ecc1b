"""The `neural_brdf` Mitsuba 3 BSDF: a flashmat neural material (.nmat).

Scene description (XML or ``mi.load_dict``)::

    <bsdf type="neural_brdf">
        <string name="filename" value="material.nmat"/>
        <string name="mode" value="texture"/>      <!-- or "pixel" (default) -->
        <string name="filter" value="nearest"/>    <!-- texture mode: or "bilinear" -->
        <integer name="pixel_x" value="10"/>       <!-- pixel mode: column -->
        <integer name="pixel_y" value="20"/>       <!-- pixel mode: row (0 = top) -->
        <vector name="normal" value="0, 0.1, 1"/>  <!-- optional, pixel mode: normal correction -->
        <string name="normals" value="n.npy"/>     <!-- optional, texture mode: [H, W, 3] or [3, H, W] -->
        <string name="network" value="auto"/>      <!-- JIT variants: auto | coopvec | unrolled -->
    </bsdf>

Math (docs/NMAT.md): with wi the direction towards the light and wo towards
the camera (Mitsuba's sampled/queried ``wo`` and ``si.wi`` respectively),
out = M_render(params, ND_enc(wi, wo)) = ln(1 + R), R = exp(out) - 1
includes the cosine and a factor pi, so the BRDF is f = R / (pi cos(wi)) and
``eval`` (f times the cosine) returns R / pi. Zero below either horizon.
Sampling is cosine-weighted over the hemisphere.

The networks (network.py) are evaluated with Dr.Jit cooperative vectors
(``drjit.nn.matvec``, weights in one packed buffer: one small kernel per
network size, shared by all materials and pixels) or, with
``network="unrolled"`` or a Dr.Jit without ``drjit.nn``, as unrolled fused
multiply-adds with the weights as kernel literals (slow to compile for the
`compact` and `paper` presets). Scalar variants use numpy. On the LLVM
backend the cooperative vectors run ~10x slower inside Mitsuba's default
symbolic calls: render with ``dr.JitFlag.SymbolicCalls`` (and, for path
tracers, ``SymbolicLoops``) off (docs/MITSUBA.md).

Normal correction (``normal`` / ``normals``): the network sees R d for each
local direction d, R = [u v n] with u = normalize(x - (x . n) n), v = n x u
(correction_matrix). With no normal the directions are used as they are,
which is what M_render was trained on (docs/MITSUBA.md).
"""
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from .network import CoopVecNetwork, UnrolledNetwork, coopvec_available
from .nmat import read_nmat, reference_log_radiance
from .sampling import cosine_sampled_base

INV_PI = 1.0 / math.pi
MAX_LOG_RADIANCE = 80.0
NETWORKS = ("auto", "coopvec", "unrolled")


def correction_matrix(n):
    """R = [u v n] (columns) of the normal correction, numpy float64.

    u = normalize(x - (x . n) n) (Gram-Schmidt of the x axis against n),
    v = n x u. R maps the shading normal (0, 0, 1) to n and is the identity
    for n = (0, 0, 1). The network sees R d for a local direction d, so a
    pixel whose parameters encode the normal n responds as if that normal
    were the shading normal (docs/MITSUBA.md, "Normal correction")."""
    n = np.asarray(n, np.float64)
    n = n / np.linalg.norm(n)
    u = np.array([1.0, 0.0, 0.0]) - n[0] * n
    if np.linalg.norm(u) < 1e-6:
        raise ValueError(f"normal correction: the normal {n.tolist()} is parallel to the x axis")
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    return np.stack([u, v, n], axis=1)


def _correct(d, n):
    """R d with R = correction_matrix(n), in Dr.Jit (n: unit Vector3f)."""
    u = dr.normalize(mi.Vector3f(1.0 - n.x * n.x, -n.x * n.y, -n.x * n.z))
    v = dr.cross(n, u)
    return u * d.x + v * d.y + n * d.z


def _resolve(path):
    fr = mi.file_resolver() if hasattr(mi, "file_resolver") else mi.Thread.thread().file_resolver()
    return str(fr.resolve(path))


_CLASSES = {}


def neural_brdf_class():
    """The NeuralBRDF class for the current Mitsuba variant (mi.BSDF differs per variant)."""
    variant = mi.variant()
    if variant is None:
        raise RuntimeError("flashmat.mitsuba: set a Mitsuba variant (mi.set_variant) first")
    if variant in _CLASSES:
        return _CLASSES[variant]

    class NeuralBRDF(cosine_sampled_base()):
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
            self.network_kind = str(props.get("network", "auto"))
            if self.network_kind not in NETWORKS:
                raise ValueError(
                    f"neural_brdf ({filename}): network must be one of {', '.join(NETWORKS)}, got {self.network_kind!r}"
                )
            if self.network_kind == "coopvec" and not coopvec_available():
                raise ValueError(f"neural_brdf ({filename}): network='coopvec' needs drjit.nn (Dr.Jit >= 1.1)")

            self.normal = None
            self.normals = None
            if self.mode == "pixel":
                self.pixel_x = int(props.get("pixel_x", w // 2))
                self.pixel_y = int(props.get("pixel_y", h // 2))
                if not (0 <= self.pixel_x < w and 0 <= self.pixel_y < h):
                    raise ValueError(
                        f"neural_brdf ({filename}): pixel ({self.pixel_x}, {self.pixel_y}) outside the {w}x{h} map"
                    )
                pixel_params = self.nmat.neural_map[:, self.pixel_y, self.pixel_x].astype(np.float64)
                if "normal" in props:
                    n = np.array(list(props["normal"]), dtype=np.float64)
                    if not (np.all(np.isfinite(n)) and n[2] > 0):
                        raise ValueError(f"neural_brdf ({filename}): normal must be finite with z > 0, got {n.tolist()}")
                    correction_matrix(n)  # refuses normals parallel to x
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
                    if not (np.all(np.isfinite(n)) and np.all(n[..., 2] > 0)):
                        raise ValueError(f"neural_brdf ({filename}): normals must be finite with z > 0")
                    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
                    self.normals = n
                    self.normals_buf = mi.Float(n.reshape(-1).astype(np.float32)) if self.jit else None

            self.net = None
            if self.jit:
                fixed = pixel_params if self.mode == "pixel" else None
                use_coop = self.network_kind == "coopvec" or (self.network_kind == "auto" and coopvec_available())
                if use_coop:
                    self.net = CoopVecNetwork(self.nmat, mi.TensorXf, mi.Float, fixed)
                else:
                    self.net = UnrolledNetwork(self.nmat, fixed)

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
            return mi.Color3f(*self.net(params, wi, wo, mi.Vector3f))

        def _value(self, si, wo, active):
            """(eval value R / pi, valid mask) for Mitsuba's si.wi (camera) and wo (light), local frame."""
            cam, light = si.wi, wo
            active = active & (mi.Frame3f.cos_theta(cam) > 0) & (mi.Frame3f.cos_theta(light) > 0)
            n = self._normal(si, active)
            if n is not None:
                # Normal correction: the network sees R d, R = [u v n] (correction_matrix).
                cam, light = _correct(cam, n), _correct(light, n)
            params = None if self.mode == "pixel" else self._params(si, active)
            out = self.log_radiance(params, light, cam)
            r = dr.maximum(dr.exp(dr.minimum(out, MAX_LOG_RADIANCE)) - 1.0, 0.0)
            return dr.select(active, r * mi.Color3f(*(INV_PI * g for g in self.nmat.gain)), 0.0), active

        # ------------------------------------------------------------ BSDF API
        def traverse(self, callback):
            pass

        def parameters_changed(self, keys):
            pass

        def to_string(self):
            extra = f"pixel=({self.pixel_x}, {self.pixel_y})" if self.mode == "pixel" else f"filter={self.filter}"
            if self.net is not None:
                extra += f", network={type(self.net).__name__}"
            return (
                f"NeuralBRDF[filename={self.filename!r}, model_id={self.nmat.meta.get('model_id')!r}, "
                f"map={self.C}x{self.H}x{self.W}, mode={self.mode}, {extra}]"
            )

    _CLASSES[variant] = NeuralBRDF
    return NeuralBRDF


def NeuralBRDF(props):
    """A neural_brdf BSDF of the current variant from Mitsuba properties."""
    return neural_brdf_class()(props)
