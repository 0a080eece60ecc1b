"""The ground-truth GGX SVBRDF of flashmat (REFERENCE section 2) as a Mitsuba 3
BSDF, `flashmat_ggx`, plus a numpy reference and a reader of material maps.

Why not Mitsuba's own `principled` or `roughconductor`: flashmat's GGX is a
Lambert lobe kd/pi plus a GGX lobe with the Schlick-GGX masking term
(k = alpha / 2), the spherical-Gaussian Schlick Fresnel with an RGB F0 (ks)
and the 1e-8 / 1e-12 clamps; `roughconductor` has the exact Smith masking,
conductor Fresnel and no diffuse lobe, and `principled` has the Disney
diffuse and its own Fresnel/metallic parametrisation. Their images would
differ from the data the networks were trained on, so the comparison
spheres would mix model error with a BRDF mismatch. This BSDF reproduces
flashmat's renderer (tests: within 1e-4 of `flashmat render`).

Scene description::

    <bsdf type="flashmat_ggx">
        <string name="svbrdf" value="maps/"/>      <!-- flashmat svbrdf generate folder -->
        <integer name="index" value="1"/>          <!-- file index NNNNNNN (default: the first) -->
        <string name="mode" value="texture"/>      <!-- or "pixel" (default) -->
        <integer name="pixel_x" value="10"/>       <!-- pixel mode -->
        <integer name="pixel_y" value="20"/>
        <boolean name="flat" value="false"/>       <!-- pixel mode: use normal (0,0,1), not the map's -->
    </bsdf>

or constant parameters: ``diffuse`` and ``specular`` (linear RGB),
``roughness`` (float), ``normal`` (vector, default (0, 0, 1)).

Conventions are those of `neural_brdf`: directions in the local shading
frame, the map's pixel normal n is a perturbation in that frame (the plane's
frame is the material frame), ``eval`` returns R / pi with
R = pi f (n . wi) flashmat's radiance, zero below either horizon; UV
u -> column, v = 1 at row 0; nearest-pixel lookup. Sampling is
cosine-weighted (like the neural BSDF).
"""
import math
import re
from pathlib import Path

import numpy as np

from .constants import DOT_EPS, FRESNEL_SG_A, FRESNEL_SG_B, SPECULAR_DENOM_EPS

GAMMA = 2.2
MAPS = ("diffuse", "specular", "roughness", "normals")


# ------------------------------------------------------------------ numpy reference
def ggx_radiance(kd, ks, roughness, normal, wi, wo):
    """flashmat's R = pi f (n . wi) for rows (numpy, float64): kd, ks [N, 3],
    roughness [N], normal [N, 3] (unit), wi towards the light, wo towards
    the camera [N, 3] (unit). REFERENCE section 2, term by term."""
    kd, ks, n, wi, wo = (np.asarray(a, np.float64) for a in (kd, ks, normal, wi, wo))
    r = np.asarray(roughness, np.float64)
    h = wi + wo
    h = h / np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), 1e-12)
    dot = lambda a, b: np.maximum((a * b).sum(-1), DOT_EPS)
    noh, nov, nol, voh = dot(n, h), dot(n, wo), dot(n, wi), dot(wo, h)
    alpha = r * r
    a2 = alpha * alpha
    d = a2 / (math.pi * np.maximum(noh * noh * (a2 - 1.0) + 1.0, DOT_EPS) ** 2)
    k = np.maximum(alpha / 2.0, DOT_EPS)
    g1 = lambda x: x / (x * (1.0 - k) + k)
    g = g1(nol) * g1(nov)
    fw = np.exp2((FRESNEL_SG_A * voh + FRESNEL_SG_B) * voh)
    f = ks + (1.0 - ks) * fw[:, None]
    brdf = kd / math.pi + (d * g)[:, None] * f / (4.0 * nol * nov + SPECULAR_DENOM_EPS)[:, None]
    return brdf * (nol * math.pi)[:, None]


# ------------------------------------------------------------------ maps
def _read_image(path):
    """[H, W, C] float64 in [0, 1] for 8/16-bit files (and whether it was integer)."""
    import mitsuba as mi

    try:
        a = np.array(mi.Bitmap(str(path)))
    except Exception as e:  # Mitsuba raises RuntimeError with a long message
        raise ValueError(f"{path}: cannot read image: {str(e).splitlines()[0]}") from e
    if a.ndim == 2:
        a = a[:, :, None]
    if np.issubdtype(a.dtype, np.integer):
        return a.astype(np.float64) / np.iinfo(a.dtype).max, True
    return a.astype(np.float64), False


def load_svbrdf(folder, index=None):
    """Linear maps of one material in flashmat's MatFusion layout
    (`folder/diffuse/NNNNNNN_diffuse.png`, specular, roughness, normals), as
    `flashmat svbrdf generate` writes them and flashmat's loader reads them:
    8/16-bit diffuse and specular linearised with ^2.2, roughness = first
    channel, normal = normalize(2 c - 1). Returns a dict of float64 arrays
    kd, ks [H, W, 3], roughness [H, W], normal [H, W, 3] (unit)."""
    folder = Path(folder)
    if not (folder / "diffuse").is_dir():
        raise ValueError(f"{folder}: not a material folder (no diffuse/ inside; expected flashmat svbrdf generate's layout)")
    if index is None:
        names = sorted(p.name for p in (folder / "diffuse").iterdir() if re.fullmatch(r"\d{7}_diffuse\.\w+", p.name))
        if not names:
            raise ValueError(f"{folder}/diffuse: no NNNNNNN_diffuse.* file")
        index = int(names[0][:7])
    out = {}
    for m in MAPS:
        files = sorted((folder / m).glob(f"{int(index):07d}_{m}.*"))
        if not files:
            raise ValueError(f"{folder}/{m}: no {int(index):07d}_{m}.* file")
        a, integer = _read_image(files[0])
        if m in ("diffuse", "specular"):
            rgb = a[:, :, :3] if a.shape[2] >= 3 else np.repeat(a[:, :, :1], 3, axis=2)
            out["kd" if m == "diffuse" else "ks"] = np.maximum(rgb, 0.0) ** GAMMA if integer else rgb
        elif m == "roughness":
            out["roughness"] = a[:, :, 0]
        else:
            if a.shape[2] < 3:
                raise ValueError(f"{files[0]}: normal map has {a.shape[2]} channel(s), expected RGB")
            n = 2.0 * a[:, :, :3] - 1.0
            out["normal"] = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    shapes = {k: v.shape[:2] for k, v in out.items()}
    if len(set(shapes.values())) != 1:
        raise ValueError(f"{folder}: maps of different sizes {shapes}")
    return out


# ------------------------------------------------------------------ Mitsuba BSDF
_CLASSES = {}


def flashmat_ggx_class():
    """The GGX BSDF class for the current Mitsuba variant."""
    import drjit as dr
    import mitsuba as mi

    from .sampling import cosine_sampled_base

    variant = mi.variant()
    if variant is None:
        raise RuntimeError("flashmat.mitsuba: set a Mitsuba variant (mi.set_variant) first")
    if variant in _CLASSES:
        return _CLASSES[variant]

    def _resolve(path):
        fr = mi.file_resolver() if hasattr(mi, "file_resolver") else mi.Thread.thread().file_resolver()
        return str(fr.resolve(path))

    class FlashmatGGX(cosine_sampled_base()):
        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            if "spectral" in mi.variant() or "mono" in mi.variant():
                raise ValueError(f"flashmat_ggx renders RGB: use an *_rgb variant, not {mi.variant()}")
            self.jit = dr.is_jit_v(mi.Float)
            self.mode = str(props.get("mode", "pixel"))
            if self.mode not in ("pixel", "texture"):
                raise ValueError(f"flashmat_ggx: mode must be 'pixel' or 'texture', got {self.mode!r}")
            self.source = None
            if "svbrdf" in props:
                self.source = _resolve(str(props["svbrdf"]))
                index = int(props["index"]) if "index" in props else None
                maps = load_svbrdf(self.source, index)
                self.H, self.W = maps["roughness"].shape
                if self.mode == "pixel":
                    j = int(props.get("pixel_x", self.W // 2))
                    i = int(props.get("pixel_y", self.H // 2))
                    if not (0 <= j < self.W and 0 <= i < self.H):
                        raise ValueError(f"flashmat_ggx ({self.source}): pixel ({j}, {i}) outside the {self.W}x{self.H} map")
                    self.pixel = (j, i)
                    self.const = {k: np.atleast_1d(v[i, j]) for k, v in maps.items()}
                    if bool(props.get("flat", False)):
                        self.const["normal"] = np.array([0.0, 0.0, 1.0])
                else:
                    self.maps = maps
                    if self.jit:
                        stacked = np.concatenate(
                            [maps["kd"], maps["ks"], maps["roughness"][:, :, None], maps["normal"]], axis=2
                        )  # [H, W, 10]
                        self.buf = mi.Float(stacked.astype(np.float32).reshape(-1))
            else:
                if self.mode == "texture":
                    raise ValueError("flashmat_ggx: texture mode needs the `svbrdf` folder")
                n = np.array(list(props.get("normal", [0.0, 0.0, 1.0])), np.float64)
                if not (np.all(np.isfinite(n)) and n[2] > 0):
                    raise ValueError(f"flashmat_ggx: normal must be finite with z > 0, got {n.tolist()}")
                self.const = {
                    "kd": np.array(list(props.get("diffuse", [0.5, 0.5, 0.5])), np.float64),
                    "ks": np.array(list(props.get("specular", [0.04, 0.04, 0.04])), np.float64),
                    "roughness": np.array([float(props.get("roughness", 0.5))]),
                    "normal": n / np.linalg.norm(n),
                }
            flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
            self.m_components = [flags]
            self.m_flags = flags

        def _material(self, si, active):
            """(kd, ks, roughness, normal) as Dr.Jit values for the interaction."""
            if self.mode == "pixel":
                c = self.const
                return (mi.Color3f(*[float(x) for x in c["kd"]]), mi.Color3f(*[float(x) for x in c["ks"]]),
                        mi.Float(float(c["roughness"][0])), mi.Vector3f(*[float(x) for x in c["normal"]]))
            w, h = self.W, self.H
            j = dr.clip(mi.Int32(dr.floor(si.uv.x * w)), 0, w - 1)
            i = dr.clip(mi.Int32(dr.floor((1.0 - si.uv.y) * h)), 0, h - 1)
            if not self.jit:
                m = self.maps
                i, j = int(i), int(j)
                return (mi.Color3f(*m["kd"][i, j]), mi.Color3f(*m["ks"][i, j]), mi.Float(m["roughness"][i, j]),
                        mi.Vector3f(*m["normal"][i, j]))
            base = mi.UInt32(i * w + j) * 10
            g = [dr.gather(mi.Float, self.buf, base + k, active) for k in range(10)]
            return mi.Color3f(g[0], g[1], g[2]), mi.Color3f(g[3], g[4], g[5]), g[6], mi.Vector3f(g[7], g[8], g[9])

        def _value(self, si, wo, active):
            cam, light = si.wi, wo
            active = active & (mi.Frame3f.cos_theta(cam) > 0) & (mi.Frame3f.cos_theta(light) > 0)
            kd, ks, rough, n = self._material(si, active)
            h = dr.normalize(cam + light)
            noh = dr.maximum(dr.dot(n, h), DOT_EPS)
            nov = dr.maximum(dr.dot(n, cam), DOT_EPS)
            nol = dr.maximum(dr.dot(n, light), DOT_EPS)
            voh = dr.maximum(dr.dot(cam, h), DOT_EPS)
            alpha = rough * rough
            a2 = alpha * alpha
            den = dr.maximum(noh * noh * (a2 - 1.0) + 1.0, DOT_EPS)
            d = a2 / (math.pi * den * den)
            k = dr.maximum(alpha * 0.5, DOT_EPS)
            g = (nol / (nol * (1.0 - k) + k)) * (nov / (nov * (1.0 - k) + k))
            fw = dr.exp2((FRESNEL_SG_A * voh + FRESNEL_SG_B) * voh)
            f = ks + (1.0 - ks) * fw
            brdf = kd * (1.0 / math.pi) + f * (d * g / (4.0 * nol * nov + SPECULAR_DENOM_EPS))
            # eval = R / pi = f (n . wi)
            return dr.select(active, brdf * nol, 0.0), active

        def traverse(self, callback):
            pass

        def parameters_changed(self, keys):
            pass

        def to_string(self):
            where = f"svbrdf={self.source!r}" if self.source else "constant"
            return f"FlashmatGGX[{where}, mode={self.mode}]"

    _CLASSES[variant] = FlashmatGGX
    return FlashmatGGX
