//! Writing a fit as texture sets other tools read.
//!
//! ```text
//! DIR/fit.json            settings, errors, timings, the conversions below
//! DIR/error.png, .exr     per-pixel fit error |ln(1+R) diff| (PNG: heat map, 0 black .. ERROR_SCALE white-yellow)
//! DIR/maps/               Blender / Unreal / Substance texture folder + README.md naming each colour space,
//!                         with height.png/.exr and ao.png ([`super::relief`]; the height's scale in README.md)
//! DIR/svbrdf/             the MatFusion layout flashmat reads (`flashmat render --svbrdf DIR/svbrdf`)
//! DIR/gltf/material.gltf  a textured 2x2 square (glTF 2.0, metallic-roughness) + square.bin + its textures;
//!                         AO in the red channel of metallic_roughness.png (glTF's occlusion-roughness-metallic packing)
//! ```
//!
//! The folder is written under a temporary name beside DIR and renamed
//! into place at the end, so a failed run leaves no partial folder; an
//! existing DIR is replaced only when it is an earlier fit (holds
//! fit.json) or empty.
//!
//! Conversions (all per pixel):
//! - roughness: flashmat's r has alpha = r^2 (REFERENCE section 2), the
//!   same as glTF's, Blender's, Unreal's and Substance's perceptual
//!   roughness, so it is written unchanged;
//! - normals: the plane's frame (x right, y up, z out of the material) is
//!   the square's tangent frame (tangent +x, bitangent +y), so the normal
//!   map is OpenGL-convention (green = +y up), encoded (n + 1) / 2;
//! - specular/diffuse to metallic/base colour: glTF models a pixel as
//!   diffuse (1 - m) c and F0 = 0.04 (1 - m) + m c. [`to_metallic`] picks
//!   per pixel the metallic m (a grid of [`METALLIC_STEPS`] values) and
//!   base colour c (least squares for that m, clamped to [0, 1]) that
//!   minimise the squared error of both kd and ks; [`from_metallic`] is the
//!   inverse a viewer applies. A dielectric pixel (ks = 0.04, grey) maps
//!   exactly to m = 0, c = kd; coloured or strong dielectric speculars are
//!   approximated, and fit.json reports what that costs in renders.

use super::relief::{ambient_occlusion, height_map, normalized_height, ReliefConfig};
use super::{FitReport, FitResult};
use crate::image::Image;
use crate::io::{write_exr, write_png, BitDepth};
use crate::spaces::srgb_encode;
use crate::svbrdf::Svbrdf;
use anyhow::{anyhow, bail, ensure, Context, Result};
use serde::{Deserialize, Serialize};
use serde_json::json;
use std::path::{Path, PathBuf};
use tch::{Kind, Tensor};

/// Reflectance at normal incidence of glTF's dielectrics (IOR 1.5).
pub const DIELECTRIC_F0: f64 = 0.04;
/// Metallic values tried per pixel by [`to_metallic`].
pub const METALLIC_STEPS: i64 = 101;
/// Error (mean |ln(1+R) diff|) shown as the top of the heat map.
pub const ERROR_SCALE: f64 = 0.1;
/// The MatFusion index of the exported material (`0000001_diffuse.png` ...).
pub const SVBRDF_INDEX: usize = 1;

/// Folder and file names inside DIR.
pub const MAPS_DIR: &str = "maps";
pub const SVBRDF_DIR: &str = "svbrdf";
pub const GLTF_DIR: &str = "gltf";
pub const GLTF_FILE: &str = "material.gltf";
pub const GLTF_BUFFER: &str = "square.bin";
pub const REPORT_FILE: &str = "fit.json";

/// Splits maps `[10, H, W]` into (kd, ks, roughness, normal) slices.
pub fn parts(maps: &Tensor) -> (Tensor, Tensor, Tensor, Tensor) {
    (maps.narrow(0, 0, 3), maps.narrow(0, 3, 3), maps.narrow(0, 6, 1), maps.narrow(0, 7, 3))
}

/// Specular/diffuse to metallic/base colour (see the module docs).
/// kd, ks: `[3, H, W]` linear -> (base colour `[3, H, W]` linear in [0, 1], metallic `[1, H, W]`).
pub fn to_metallic(kd: &Tensor, ks: &Tensor) -> (Tensor, Tensor) {
    tch::no_grad(|| {
        let opts = (Kind::Float, kd.device());
        let (kd, ks) = (kd.to_kind(Kind::Float).unsqueeze(0), ks.to_kind(Kind::Float).unsqueeze(0)); // [1, 3, H, W]
        let m = Tensor::linspace(0.0, 1.0, METALLIC_STEPS, opts).view([METALLIC_STEPS, 1, 1, 1]);
        let dielectric = (1.0 - &m) * DIELECTRIC_F0;
        let one_m = 1.0 - &m;
        let c = ((&one_m * &kd + &m * (&ks - &dielectric)) / (one_m.square() + m.square())).clamp(0.0, 1.0); // [M, 3, H, W]
        let err = ((&one_m * &c - &kd).square() + (&m * &c + &dielectric - &ks).square()).sum_dim_intlist([1i64].as_slice(), true, Kind::Float); // [M, 1, H, W]
        let best = err.argmin(0, true); // [1, 1, H, W]
        let s = c.size();
        let base = c.gather(0, &best.expand([1, 3, s[2], s[3]], false), false).get(0);
        let metallic = m.expand([METALLIC_STEPS, 1, s[2], s[3]], false).gather(0, &best, false).get(0);
        (base, metallic)
    })
}

/// Metallic/base colour to the GGX model's albedos, as glTF defines them:
/// kd = (1 - m) c, ks = 0.04 (1 - m) + m c.
/// base: `[3, H, W]`, metallic: `[1, H, W]` -> (kd, ks) `[3, H, W]`.
pub fn from_metallic(base: &Tensor, metallic: &Tensor) -> (Tensor, Tensor) {
    let kd = (1.0 - metallic) * base;
    let ks = (1.0 - metallic) * DIELECTRIC_F0 + metallic * base;
    (kd, ks)
}

/// The metallic-roughness texture set of a fit, linear values.
pub struct MetallicRoughness {
    /// `[3, H, W]` linear base colour.
    pub base_color: Tensor,
    /// `[1, H, W]`.
    pub metallic: Tensor,
    /// `[1, H, W]` (alpha = r^2, as flashmat's).
    pub roughness: Tensor,
    /// `[3, H, W]` unit normals, OpenGL convention.
    pub normal: Tensor,
}

impl MetallicRoughness {
    /// maps: `[10, H, W]` (fitted GGX maps).
    pub fn from_maps(maps: &Tensor) -> Self {
        let (kd, ks, roughness, normal) = parts(maps);
        let (base_color, metallic) = to_metallic(&kd, &ks);
        Self { base_color, metallic, roughness: roughness.shallow_clone(), normal: normal.shallow_clone() }
    }

    /// The GGX maps `[10, H, W]` this texture set stands for.
    pub fn to_maps(&self) -> Tensor {
        let (kd, ks) = from_metallic(&self.base_color, &self.metallic);
        Tensor::cat(&[kd, ks, self.roughness.shallow_clone(), self.normal.shallow_clone()], 0)
    }
}

/// Mean |ln(1 + R) diff| between renders of two map sets over the fit's
/// direction pairs. a, b: `[10, H, W]`; wi, wo: `[S, 3]`.
pub fn render_difference(a: &Tensor, b: &Tensor, wi: &Tensor, wo: &Tensor) -> f64 {
    tch::no_grad(|| (super::ggx_log(&a.unsqueeze(0), wi, wo) - super::ggx_log(&b.unsqueeze(0), wi, wo)).abs().mean(Kind::Double).double_value(&[]))
}

/// Heat-map colours: black, purple, orange, pale yellow.
const HEAT_STOPS: [[f32; 3]; 4] = [[0.0, 0.0, 0.0], [0.45, 0.1, 0.55], [0.95, 0.45, 0.1], [1.0, 1.0, 0.75]];

/// Display colours of an error map: error `[H, W]` -> `[3, H, W]` in [0, 1],
/// 0 black to [`ERROR_SCALE`] (and above) pale yellow.
pub fn heat_map(error: &Tensor) -> Result<Image> {
    let e = Image::from_tensor(&error.unsqueeze(0))?;
    let stops = HEAT_STOPS.len() - 1;
    let mut out = Image::new(3, e.height, e.width);
    for y in 0..e.height {
        for x in 0..e.width {
            let t = (e.get(0, y, x) / ERROR_SCALE as f32).clamp(0.0, 1.0) * stops as f32;
            let i = (t.floor() as usize).min(stops - 1);
            let f = t - i as f32;
            for c in 0..3 {
                out.set(c, y, x, HEAT_STOPS[i][c] * (1.0 - f) + HEAT_STOPS[i + 1][c] * f);
            }
        }
    }
    Ok(out)
}

fn image(t: &Tensor) -> Result<Image> {
    Image::from_tensor(t)
}

fn srgb(t: &Tensor) -> Result<Image> {
    Ok(image(t)?.map(srgb_encode))
}

/// (n + 1) / 2 of unit normals `[3, H, W]`.
fn encoded_normal(n: &Tensor) -> Result<Image> {
    Ok(image(n)?.map(|v| ((v + 1.0) * 0.5).clamp(0.0, 1.0)))
}

/// Height and AO of the fitted maps ([`super::relief`]).
pub struct Relief {
    /// `[1, H, W]` plane units, mean zero.
    pub height: Image,
    /// `[1, H, W]` in [0, 1].
    pub ao: Image,
}

impl Relief {
    /// normals: `[3, H, W]` unit vectors.
    pub fn from_normals(normals: &Tensor, cfg: &ReliefConfig) -> Result<Self> {
        let height = height_map(&image(normals)?)?;
        let ao = ambient_occlusion(&height, cfg)?;
        Ok(Self { height, ao })
    }

    /// (lowest, highest) height in plane units: what height.png's 0 and 65535 stand for.
    pub fn range(&self) -> (f32, f32) {
        let (_, lo, hi) = normalized_height(&self.height);
        (lo, hi)
    }
}

/// What the export wrote, for fit.json.
#[derive(Clone, Debug, Serialize, Deserialize)]
pub struct ExportReport {
    pub fit: FitReport,
    /// Where the material came from (a .nmat or photo path).
    pub source: String,
    pub width: usize,
    pub height: usize,
    /// Mean |ln(1+R) diff| over the fit's direction pairs between the fitted
    /// maps and the glTF material (metallic conversion and 8-bit quantisation).
    pub gltf_conversion_error: f64,
    /// Mean metallic of the glTF material.
    pub mean_metallic: f64,
    pub error_scale: f64,
    /// Heights (plane units) of height.png's 0 and 65535.
    pub height_range: [f32; 2],
    /// Mean AO of ao.png.
    pub mean_ao: f64,
    pub relief: ReliefConfig,
    pub conventions: serde_json::Value,
}

/// The texture set of a fit, as a viewer decodes it after 8-bit storage:
/// base colour sRGB-quantised, metallic, roughness and normals quantised to
/// 8 bits. maps: `[10, H, W]` -> `[10, H, W]`.
pub fn quantized_gltf_maps(maps: &Tensor) -> Result<Tensor> {
    let mr = MetallicRoughness::from_maps(maps);
    let q = |t: &Tensor| (t.clamp(0.0, 1.0) * 255.0).round() / 255.0;
    let base = Image::from_tensor(&mr.base_color)?.map(|v| crate::spaces::srgb_decode((srgb_encode(v) * 255.0).round() / 255.0));
    let normal = crate::geometry::normalize_channels(&(q(&((&mr.normal + 1.0) * 0.5)) * 2.0 - 1.0).unsqueeze(0)).get(0);
    let back = MetallicRoughness { base_color: base.to_tensor(), metallic: q(&mr.metallic), roughness: q(&mr.roughness), normal };
    Ok(back.to_maps())
}

/// Writes the Blender/Unreal/Substance folder: PNG (8-bit; colour maps
/// sRGB, data maps linear) and EXR (float, linear) maps and a README.
fn write_maps_folder(dir: &Path, maps: &Tensor, mr: &MetallicRoughness, relief: &Relief, relief_cfg: &ReliefConfig) -> Result<()> {
    std::fs::create_dir(dir).with_context(|| format!("cannot create folder {}", dir.display()))?;
    let (kd, ks, rough, normal) = parts(maps);
    let png = |name: &str, im: Image| write_png(&dir.join(name), &im, BitDepth::Eight);
    let exr = |name: &str, t: &Tensor| write_exr(&dir.join(name), &image(t)?);
    png("diffuse.png", srgb(&kd)?)?;
    png("specular.png", srgb(&ks)?)?;
    png("roughness.png", image(&rough)?)?;
    png("normal.png", encoded_normal(&normal)?)?;
    // DirectX convention (Unreal): green = -y.
    let dx = Tensor::cat(&[normal.narrow(0, 0, 1), -normal.narrow(0, 1, 1), normal.narrow(0, 2, 1)], 0);
    png("normal_directx.png", encoded_normal(&dx)?)?;
    png("base_color.png", srgb(&mr.base_color)?)?;
    png("metallic.png", image(&mr.metallic)?)?;
    exr("diffuse.exr", &kd)?;
    exr("specular.exr", &ks)?;
    exr("roughness.exr", &rough)?;
    exr("normal.exr", &normal)?;
    exr("base_color.exr", &mr.base_color)?;
    exr("metallic.exr", &mr.metallic)?;
    let (height, lo, hi) = normalized_height(&relief.height);
    write_png(&dir.join("height.png"), &height, BitDepth::Sixteen)?;
    write_exr(&dir.join("height.exr"), &relief.height)?;
    png("ao.png", relief.ao.clone())?;
    let (h, w) = (relief.height.height, relief.height.width);
    crate::io::atomic_write_bytes(&dir.join("README.md"), format!("{MAPS_README}{}", height_readme(lo, hi, h, w, relief_cfg)).as_bytes())
}

/// The README's height section: this fit's scale.
fn height_readme(lo: f32, hi: f32, h: usize, w: usize, cfg: &ReliefConfig) -> String {
    let range = hi - lo;
    let short = h.min(w);
    format!(
        "
## Height and ambient occlusion of this fit

`height.png` (16-bit grey, linear) maps 0 .. 65535 to heights {lo:.6} .. {hi:.6}
plane units, a relief of **{range:.6}** plane units, where the material's
shorter side is 2 plane units ({short} pixels): the relief is **{pct:.3}%** of
the shorter side, {px:.3} pixels. `height.exr` holds the heights themselves
(plane units, mean 0). In Blender, a Displacement node with Midlevel 0 and
Scale = {range:.6} x (the object's size across the shorter side / 2) gives
the fitted relief on the material's 2 x 2 square (`../gltf/material.gltf`);
Unreal (World Position Offset / Nanite displacement, magnitude = the same
scale) and Unity (HDRP/URP height map: set the amplitude to the same
scale) alike. The height is integrated from the fitted normals
(least-squares, so it only holds their relief: its offset is arbitrary).

`ao.png` (8-bit, linear, Non-Color): ambient occlusion of that height field,
the cosine-weighted fraction of the sky above each pixel that the relief
leaves open (1 = open, from {dirs} fixed directions; rays leaving the
material count as open), with the relief multiplied by {depth} (`--ao-depth`;
1 is the fitted relief: nearly flat materials give AO near 1 everywhere). glTF reads it as `occlusionTexture` from the red
channel of `../gltf/metallic_roughness.png`. For a rectangle the occlusion
march treats the material as square (the longer side squeezed).
",
        pct = range / 2.0 * 100.0,
        px = range / 2.0 * short as f32,
        dirs = cfg.ao_directions,
        depth = cfg.ao_depth,
    )
}

/// The README of the texture folder.
pub const MAPS_README: &str = "# Texture set fitted by `flashmat fit`

GGX maps fitted per pixel to a neural material, in two workflows. Roughness is
perceptual roughness (alpha = roughness^2) in both flashmat and Blender /
glTF / Unreal / Substance, so it needs no conversion.

| file | what | colour space to set |
|---|---|---|
| `base_color.png` | metallic workflow: base colour | **sRGB** |
| `metallic.png` | metallic workflow: metalness (0 dielectric, 1 metal) | **Non-Color** (linear) |
| `roughness.png` | roughness (both workflows) | **Non-Color** (linear) |
| `normal.png` | tangent-space normal map, OpenGL convention (green = up, +Y); Blender, glTF, Substance (OpenGL) | **Non-Color** (linear) |
| `normal_directx.png` | the same, DirectX convention (green = down, -Y): Unreal, Substance (DirectX) | **Non-Color** (linear) |
| `diffuse.png` | specular workflow: diffuse albedo kd | **sRGB** |
| `specular.png` | specular workflow: specular albedo ks (F0, reflectance at normal incidence) | **sRGB** |
| `height.png` | height integrated from the normals, 16-bit, 0 .. 65535 = lowest .. highest (scale below); displacement / parallax / height slots | **Non-Color** (linear) |
| `ao.png` | ambient occlusion of that height (1 = unoccluded); AO slots | **Non-Color** (linear) |
| `*.exr` | the same maps as float (linear values; `normal.exr` holds the unit vector x, y, z in [-1, 1], not encoded) | **Linear** / Non-Color |

PNG colour maps use the sRGB transfer function; PNG data maps hold linear
values; normals are stored as (n + 1) / 2.

Blender (Principled BSDF): `base_color.png` -> Base Color (sRGB);
`metallic.png` -> Metallic, `roughness.png` -> Roughness (Non-Color);
`normal.png` (Non-Color) -> Normal Map node (Tangent Space) -> Normal.
The material spans 2 x 2 units (a rectangle: 2 across its shorter side,
2a across the longer) with its UV (0, 0) at the top left
of the images (as glTF). Or import `../gltf/material.gltf`, which holds
the same maps wired up.

Unreal: base colour sRGB on, metallic/roughness sRGB off,
`normal_directx.png` as a Normalmap texture (or `normal.png` with Flip
Green Channel). Substance: choose the OpenGL or DirectX normal map to
match the project's setting.

The metallic workflow cannot hold every GGX material exactly: per pixel,
metallic m and base colour c were chosen so that (1 - m) c (diffuse) and
0.04 (1 - m) + m c (F0) are closest to the fitted diffuse and specular;
`../fit.json` gives what this costs (`gltf_conversion_error`).
";

/// Writes the glTF 2.0 square: `material.gltf`, `square.bin` (positions,
/// normals, tangents, UVs, indices) and three textures.
fn write_gltf(dir: &Path, mr: &MetallicRoughness, ao: &Image, name: &str) -> Result<()> {
    std::fs::create_dir(dir).with_context(|| format!("cannot create folder {}", dir.display()))?;
    let s = mr.base_color.size();
    let (h, w) = (s[1], s[2]);
    write_png(&dir.join("base_color.png"), &srgb(&mr.base_color)?, BitDepth::Eight)?;
    // glTF's metallicRoughness texture: G = roughness, B = metallic; R (unused by it) holds the occlusion texture.
    let orm = Tensor::cat(&[ao.to_tensor().to_device(mr.metallic.device()), mr.roughness.to_kind(Kind::Float), mr.metallic.to_kind(Kind::Float)], 0);
    write_png(&dir.join("metallic_roughness.png"), &image(&orm)?, BitDepth::Eight)?;
    write_png(&dir.join("normal.png"), &encoded_normal(&mr.normal)?, BitDepth::Eight)?;

    // The material at z = 0 facing +z: [-1, 1]^2 for square maps, else the
    // shorter side [-1, 1] and the longer [-a, a] (geometry::half_extents),
    // so texels stay square; UV (0, 0) is the images' top left.
    let (ax, ay) = crate::geometry::half_extents(h as usize, w as usize);
    let (ax, ay) = (ax as f32, ay as f32);
    let positions: [[f32; 3]; 4] = [[-ax, -ay, 0.0], [ax, -ay, 0.0], [ax, ay, 0.0], [-ax, ay, 0.0]];
    let uvs: [[f32; 2]; 4] = positions.map(|p| [(p[0] / ax + 1.0) / 2.0, (1.0 - p[1] / ay) / 2.0]);
    let indices: [u16; 6] = [0, 1, 2, 0, 2, 3];
    let mut bin: Vec<u8> = Vec::new();
    let mut views = Vec::new();
    let mut push = |bytes: Vec<u8>, target: u32| {
        views.push(json!({"buffer": 0, "byteOffset": bin.len(), "byteLength": bytes.len(), "target": target}));
        bin.extend(bytes);
    };
    let floats = |v: &[f32]| v.iter().flat_map(|f| f.to_le_bytes()).collect::<Vec<u8>>();
    push(floats(&positions.concat()), 34962);
    push(floats(&[0.0f32, 0.0, 1.0].repeat(4)), 34962);
    push(floats(&[1.0f32, 0.0, 0.0, 1.0].repeat(4)), 34962);
    push(floats(&uvs.concat()), 34962);
    push(indices.iter().flat_map(|i| i.to_le_bytes()).collect(), 34963);
    let accessor = |view: usize, count: usize, ty: &str, component: u32| json!({"bufferView": view, "componentType": component, "count": count, "type": ty});
    let mut position = accessor(0, 4, "VEC3", 5126);
    position["min"] = json!([-ax, -ay, 0.0]);
    position["max"] = json!([ax, ay, 0.0]);
    let doc = json!({
        "asset": {"version": "2.0", "generator": format!("flashmat fit {}", env!("CARGO_PKG_VERSION"))},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": "material square"}],
        "meshes": [{"name": "square", "primitives": [{
            "attributes": {"POSITION": 0, "NORMAL": 1, "TANGENT": 2, "TEXCOORD_0": 3},
            "indices": 4, "material": 0, "mode": 4}]}],
        "materials": [{
            "name": name,
            "pbrMetallicRoughness": {
                "baseColorFactor": [1.0, 1.0, 1.0, 1.0],
                "baseColorTexture": {"index": 0, "texCoord": 0},
                "metallicFactor": 1.0,
                "roughnessFactor": 1.0,
                "metallicRoughnessTexture": {"index": 1, "texCoord": 0}
            },
            "normalTexture": {"index": 2, "texCoord": 0, "scale": 1.0},
            "occlusionTexture": {"index": 1, "texCoord": 0, "strength": 1.0}
        }],
        "textures": [{"sampler": 0, "source": 0}, {"sampler": 0, "source": 1}, {"sampler": 0, "source": 2}],
        "images": [{"uri": "base_color.png", "mimeType": "image/png"}, {"uri": "metallic_roughness.png", "mimeType": "image/png"}, {"uri": "normal.png", "mimeType": "image/png"}],
        // LINEAR / LINEAR_MIPMAP_LINEAR, CLAMP_TO_EDGE.
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}],
        "buffers": [{"uri": GLTF_BUFFER, "byteLength": bin.len()}],
        "bufferViews": views,
        "accessors": [position, accessor(1, 4, "VEC3", 5126), accessor(2, 4, "VEC4", 5126), accessor(3, 4, "VEC2", 5126), accessor(4, 6, "SCALAR", 5123)]
    });
    crate::io::atomic_write_bytes(&dir.join(GLTF_BUFFER), &bin)?;
    crate::io::atomic_write_bytes(&dir.join(GLTF_FILE), serde_json::to_string_pretty(&doc)?.as_bytes())
}

/// The conventions fit.json records.
fn conventions() -> serde_json::Value {
    json!({
        "maps/*.png colour maps": "sRGB transfer function (diffuse, specular, base_color)",
        "maps/*.png data maps": "linear (roughness, metallic, ao); normals (n + 1) / 2, OpenGL (+y up) and DirectX (normal_directx.png); height.png 16-bit, 0 .. 65535 = height_range",
        "height": "least-squares integral of the fitted normals (svbrdf::height), plane units (shorter side 2), mean 0; offset arbitrary",
        "ao": "mean visibility over cosine-distributed hemisphere directions (relief.ao_directions) of the height field's shadow march; glTF occlusionTexture = red channel of metallic_roughness.png",
        "svbrdf/": "MatFusion layout as flashmat reads it: diffuse and specular gamma 2.2 encoded, roughness linear, normals (n + 1) / 2",
        "roughness": "alpha = roughness^2 in flashmat (REFERENCE section 2) and in glTF, Blender, Unreal, Substance: written unchanged",
        "metallic": "per pixel m, c minimising |(1 - m) c - kd|^2 + |0.04 (1 - m) + m c - ks|^2 over m in {0, 0.01, ..., 1}",
        "error": "per pixel mean over the direction pairs and RGB of |ln(1 + R_ggx) - ln(1 + R_neural)|; error.png maps 0 .. error_scale to black .. pale yellow"
    })
}

/// Folders that `create_parents` made, removed again (while empty) when
/// dropped without `keep`.
struct CreatedParents(Vec<PathBuf>);

impl CreatedParents {
    fn keep(mut self) {
        self.0.clear();
    }
}

impl Drop for CreatedParents {
    fn drop(&mut self) {
        for d in &self.0 {
            let _ = std::fs::remove_dir(d);
        }
    }
}

fn create_parents(dir: &Path) -> Result<CreatedParents> {
    let mut created = CreatedParents(Vec::new());
    let mut missing = Some(dir);
    while let Some(d) = missing.filter(|d| !d.as_os_str().is_empty() && std::fs::symlink_metadata(d).is_err()) {
        created.0.push(d.to_path_buf());
        missing = d.parent();
    }
    std::fs::create_dir_all(dir).map_err(|e| anyhow!("cannot create output folder {}: {e}", dir.display()))?;
    Ok(created)
}

/// Removes a temporary folder unless disarmed.
struct TempDir(Option<PathBuf>);

impl Drop for TempDir {
    fn drop(&mut self) {
        if let Some(p) = self.0.take() {
            let _ = std::fs::remove_dir_all(p);
        }
    }
}

/// Checks that `dir` can receive the export: absent, an empty folder or an
/// earlier fit's folder (holding fit.json).
pub fn check_output_dir(dir: &Path) -> Result<()> {
    match std::fs::symlink_metadata(dir) {
        Err(_) => Ok(()),
        Ok(m) if m.is_dir() => {
            let mut entries = std::fs::read_dir(dir).map_err(|e| anyhow!("cannot read output folder {}: {e}", dir.display()))?;
            if entries.next().is_none() || dir.join(REPORT_FILE).is_file() {
                Ok(())
            } else {
                bail!("output folder {} exists and is not an earlier fit (no {REPORT_FILE}); choose another folder or empty it", dir.display())
            }
        }
        Ok(_) => bail!("cannot write output folder {}: a file of that name exists", dir.display()),
    }
}

/// Writes a fit (see the module docs for the layout) to `dir`, all or
/// nothing. Returns what fit.json holds.
pub fn write_fit(dir: &Path, fit: &FitResult, relief_cfg: &ReliefConfig, source: &str) -> Result<ExportReport> {
    relief_cfg.validate()?;
    let (wi, wo) = (&fit.wi, &fit.wo);
    check_output_dir(dir)?;
    let s = fit.maps.size();
    ensure!(s.len() == 3 && s[0] == 10, "fitted maps must be [10, H, W], got {s:?}");
    let (h, w) = (s[1] as usize, s[2] as usize);
    let maps = fit.maps.to_device(tch::Device::Cpu).to_kind(Kind::Float);
    let name = dir.file_name().and_then(|n| n.to_str()).filter(|n| !n.is_empty()).unwrap_or("flashmat fit").to_string();
    let parent = match dir.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let parents = create_parents(&parent)?;
    let tmp = parent.join(format!(".{name}.tmp-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    std::fs::create_dir(&tmp).map_err(|e| anyhow!("cannot create output folder {}: {e}", dir.display()))?;
    let mut guard = TempDir(Some(tmp.clone()));

    let mr = MetallicRoughness::from_maps(&maps);
    let relief = Relief::from_normals(&mr.normal, relief_cfg)?;
    let (lo, hi) = relief.range();
    let gltf_maps = quantized_gltf_maps(&maps)?;
    let report = ExportReport {
        fit: fit.report.clone(),
        source: source.to_string(),
        width: w,
        height: h,
        gltf_conversion_error: render_difference(&maps, &gltf_maps, wi, wo),
        mean_metallic: mr.metallic.mean(Kind::Double).double_value(&[]),
        error_scale: ERROR_SCALE,
        height_range: [lo, hi],
        mean_ao: relief.ao.data.iter().map(|&v| v as f64).sum::<f64>() / relief.ao.data.len().max(1) as f64,
        relief: *relief_cfg,
        conventions: conventions(),
    };
    let write = || -> Result<()> {
        write_png(&tmp.join("error.png"), &heat_map(&fit.error)?, BitDepth::Eight)?;
        write_exr(&tmp.join("error.exr"), &image(&fit.error.unsqueeze(0))?)?;
        write_maps_folder(&tmp.join(MAPS_DIR), &maps, &mr, &relief, relief_cfg)?;
        let svbrdf = Svbrdf::from_stacked(&image(&maps)?)?;
        crate::data::loaders::write_matfusion(&tmp.join(SVBRDF_DIR), SVBRDF_INDEX, &svbrdf)?;
        write_gltf(&tmp.join(GLTF_DIR), &mr, &relief.ao, &name)?;
        crate::io::atomic_write_bytes(&tmp.join(REPORT_FILE), serde_json::to_string_pretty(&report)?.as_bytes())?;
        Ok(())
    };
    write().map_err(|e| anyhow!("cannot write {}: {e:#}", dir.display()))?;
    // Replace an earlier fit (checked above) only now that the new one is complete.
    if std::fs::symlink_metadata(dir).is_ok() {
        check_output_dir(dir)?;
        std::fs::remove_dir_all(dir).map_err(|e| anyhow!("cannot replace {}: {e}", dir.display()))?;
    }
    std::fs::rename(&tmp, dir).map_err(|e| anyhow!("cannot move the fit into {}: {e}", dir.display()))?;
    guard.0 = None;
    parents.keep();
    Ok(report)
}
