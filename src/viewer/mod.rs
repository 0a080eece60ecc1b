//! `flashmat view`: a neural material as one self-contained HTML page that
//! re-renders it live in the browser (WebGL2), with the light under the
//! mouse. See docs/VIEWER.md.
//!
//! The page embeds (base64, no network):
//! - the ND_enc + M_render weights as one RGBA16F texture: each layer's
//!   `[out, in]` matrix padded to multiples of 4 in both dimensions, texel
//!   (g, row) = `W[row][4g..4g+4]`, layers stacked by rows ([`pack_weights`]);
//! - the neural map as a texture array of ceil(C/4) RGBA layers, f16 or
//!   8-bit with a per-channel scale and offset ([`MapEncoding`]);
//! - the input photo (linear RGB, f16) for the photo toggle.
//!
//! The fragment shaders (`layer.frag`, `display.frag`) evaluate docs/NMAT.md
//! per pixel: one pass per layer and group of up to 8 x 4 output channels
//! (multiple render targets), then a display pass (exp - 1, exposure,
//! ^(1/2.2)). The HTML, JavaScript and GLSL live beside this file and are
//! compiled in with `include_str!`.

use crate::geometry::LightView;
use crate::infer::NeuralMaterial;
use crate::model::m_render::{RENDER_FINAL_SLOPE, RENDER_SLOPE};
use crate::model::nd_enc::ND_ENC_SLOPE;
use anyhow::{bail, ensure, Context, Result};
use std::collections::HashMap;
use tch::{Kind, Tensor};

const PAGE: &str = include_str!("viewer.html");
const SCRIPT: &str = include_str!("viewer.js");
const LAYER_SHADER: &str = include_str!("layer.frag");
const DISPLAY_SHADER: &str = include_str!("display.frag");

/// Format tag and version of the data block inside the page.
pub const VIEWER_FORMAT: &str = "flashmat-viewer";
pub const VIEWER_VERSION: u32 = 1;

/// How the neural map is stored in the page.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MapEncoding {
    /// IEEE half floats (2 bytes per value).
    F16,
    /// 8 bits per value, value = offset[c] + scale[c] * q / 255 per channel.
    U8,
}

/// What `--map-bits` asks for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum MapBits {
    /// 8-bit when it stays below one display level of the f32 render on the check views, else f16.
    Auto,
    #[value(name = "8")]
    Eight,
    #[value(name = "16")]
    Sixteen,
}

/// One network layer in the packed weight texture.
#[derive(Clone, Debug, PartialEq)]
pub struct PackedLayer {
    /// `nd_enc.0` .. `m_render.6`.
    pub name: String,
    /// Logical `[out, in]` of the stored matrix.
    pub out: usize,
    pub inp: usize,
    /// Padded sizes: multiples of 4 (M_render 0: ceil4(C) + ceil4(enc_out)).
    pub out_pad: usize,
    pub in_pad: usize,
    /// First texture row of the layer.
    pub row: usize,
    /// LeakyReLU slope after the layer (1 = no activation).
    pub slope: f64,
}

/// ND_enc + M_render as one RGBA texture of f16 values.
#[derive(Clone, Debug)]
pub struct PackedWeights {
    /// Texture width in texels (4 values each) and height in rows.
    pub width: usize,
    pub height: usize,
    /// f16 bits, `[height, width, 4]` row-major.
    pub data: Vec<u16>,
    pub layers: Vec<PackedLayer>,
}

fn ceil4(n: usize) -> usize {
    n.div_ceil(4) * 4
}

/// The 10 layer matrices `[out, in]` (f32, CPU) in evaluation order with
/// their names and activation slopes.
fn layer_matrices(m: &NeuralMaterial) -> Vec<(String, Tensor, f64)> {
    let r = &m.renderer;
    let mut v = Vec::new();
    let n_enc = r.nd_enc.layers.len();
    for (i, w) in r.nd_enc.layers.iter().enumerate() {
        v.push((format!("nd_enc.{i}"), w.detach().to_kind(Kind::Float).to_device(tch::Device::Cpu), if i + 1 < n_enc { ND_ENC_SLOPE } else { 1.0 }));
    }
    let n_ren = r.m_render.layers.len();
    for (i, w) in r.m_render.layers.iter().enumerate() {
        let slope = match i {
            0 => 1.0,
            i if i + 1 == n_ren => RENDER_FINAL_SLOPE,
            _ => RENDER_SLOPE,
        };
        v.push((format!("m_render.{i}"), w.detach().to_kind(Kind::Float).to_device(tch::Device::Cpu), slope));
    }
    v
}

/// Packs the renderer's weights (see the module doc). M_render 0's columns
/// are split into the parameter part (padded to ceil4(C)) and the code
/// part (padded to ceil4(enc_out)), the layout of the shader's inputs.
pub fn pack_weights(m: &NeuralMaterial) -> Result<PackedWeights> {
    let c = m.config.neural_channels as usize;
    let mut layers = Vec::new();
    let mut mats = Vec::new();
    let mut row = 0;
    for (name, w, slope) in layer_matrices(m) {
        let s = w.size();
        ensure!(s.len() == 2, "layer {name} must be a matrix, got shape {s:?}");
        let (out, inp) = (s[0] as usize, s[1] as usize);
        let in_pad = if name == "m_render.0" {
            ensure!(inp > c, "layer m_render.0 has {inp} inputs, fewer than the {c} neural channels");
            ceil4(c) + ceil4(inp - c)
        } else {
            ceil4(inp)
        };
        let out_pad = ceil4(out);
        layers.push(PackedLayer { name, out, inp, out_pad, in_pad, row, slope });
        row += out_pad;
        mats.push(w);
    }
    let width = layers.iter().map(|l| l.in_pad / 4).max().unwrap_or(1);
    let height = row;
    let mut data = vec![0u16; height * width * 4];
    for (l, w) in layers.iter().zip(&mats) {
        let vals: Vec<f32> = Vec::try_from(w.contiguous().view([-1]))?;
        for o in 0..l.out {
            for i in 0..l.inp {
                let col = if l.name == "m_render.0" && i >= c { ceil4(c) + (i - c) } else { i };
                let v = vals[o * l.inp + i];
                data[(l.row + o) * width * 4 + col] = to_f16(v).with_context(|| format!("weight {}[{o}, {i}]", l.name))?;
            }
        }
    }
    Ok(PackedWeights { width, height, data, layers })
}

/// f32 -> f16 bits (round to nearest even); values beyond the f16 range are errors.
fn to_f16(v: f32) -> Result<u16> {
    let h = half::f16::from_f32(v);
    if !h.is_finite() {
        bail!("{v} does not fit in a 16-bit float (largest 65504)");
    }
    Ok(h.to_bits())
}

/// Channel-first `[C, H, W]` -> texture-array order `[ceil(C/4), H, W, 4]`
/// (zero-padded channels); row 0 is the top row.
fn to_layers<T: Copy + Default>(values: &[T], c: usize, h: usize, w: usize) -> Vec<T> {
    let layers = c.div_ceil(4);
    let mut out = vec![T::default(); layers * h * w * 4];
    for ch in 0..c {
        let (l, comp) = (ch / 4, ch % 4);
        for p in 0..h * w {
            out[(l * h * w + p) * 4 + comp] = values[ch * h * w + p];
        }
    }
    out
}

/// A neural map `[C, H, W]` as f16 bits in texture-array order.
pub fn pack_map_f16(map: &Tensor) -> Result<Vec<u16>> {
    let s = map.size();
    ensure!(s.len() == 3, "neural map must be [C, H, W], got {s:?}");
    let vals: Vec<f32> = Vec::try_from(map.to_kind(Kind::Float).to_device(tch::Device::Cpu).contiguous().view([-1]))?;
    let bits = vals.iter().map(|&v| to_f16(v)).collect::<Result<Vec<u16>>>().context("the neural map cannot be stored as f16")?;
    Ok(to_layers(&bits, s[0] as usize, s[1] as usize, s[2] as usize))
}

/// An 8-bit neural map: value = offset[c] + scale[c] * q / 255.
#[derive(Debug)]
pub struct U8Map {
    /// Codes in texture-array order `[ceil(C/4), H, W, 4]`.
    pub data: Vec<u8>,
    /// Per channel (C entries): the channel's minimum and max - min.
    pub offset: Vec<f32>,
    pub scale: Vec<f32>,
    /// The decoded map `[C, H, W]` (f32), what the page sees.
    pub decoded: Tensor,
}

/// Quantises each channel of a map `[C, H, W]` to 256 levels between its
/// minimum and maximum.
pub fn pack_map_u8(map: &Tensor) -> Result<U8Map> {
    let s = map.size();
    ensure!(s.len() == 3, "neural map must be [C, H, W], got {s:?}");
    let (c, h, w) = (s[0] as usize, s[1] as usize, s[2] as usize);
    let vals: Vec<f32> = Vec::try_from(map.to_kind(Kind::Float).to_device(tch::Device::Cpu).contiguous().view([-1]))?;
    let (mut offset, mut scale) = (Vec::with_capacity(c), Vec::with_capacity(c));
    let mut codes = vec![0u8; vals.len()];
    let mut decoded = vec![0f32; vals.len()];
    for ch in 0..c {
        let plane = &vals[ch * h * w..(ch + 1) * h * w];
        let lo = plane.iter().copied().fold(f32::INFINITY, f32::min);
        let hi = plane.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        let range = hi - lo;
        for (p, &v) in plane.iter().enumerate() {
            let q = if range > 0.0 { ((v - lo) / range * 255.0).round().clamp(0.0, 255.0) } else { 0.0 };
            codes[ch * h * w + p] = q as u8;
            // As the shader decodes it: the texture unit returns q / 255.
            decoded[ch * h * w + p] = lo + range * (q / 255.0);
        }
        offset.push(lo);
        scale.push(range);
    }
    let decoded = Tensor::from_slice(&decoded).view([c as i64, h as i64, w as i64]);
    Ok(U8Map { data: to_layers(&codes, c, h, w), offset, scale, decoded })
}

/// Display-level difference between two linear renders `[K, 3, H, W]`:
/// (mean, max) of |display(a) - display(b)| x 255 with display =
/// clamp(R, 0, 1)^(1/2.2), the PNG transform of `flashmat relight`.
pub fn display_error(a: &Tensor, b: &Tensor) -> (f64, f64) {
    let d = (crate::spaces::linear_to_display(a) - crate::spaces::linear_to_display(b)).abs() * 255.0;
    (d.mean(Kind::Double).double_value(&[]), d.max().double_value(&[]))
}

/// Light/view configurations the encoding is checked on: the identity
/// view and the four orbit lights of `flashmat show`.
pub fn check_configs() -> Vec<LightView> {
    let cam = crate::infer::overhead_camera();
    let mut v = vec![NeuralMaterial::identity_config()];
    v.extend(crate::infer::orbit_configs(4, crate::infer::ORBIT_RADIUS, crate::infer::ORBIT_HEIGHT, cam));
    v
}

/// The material as the page evaluates it: weights rounded to f16 and the
/// given map `[C, H, W]` (already decoded from its stored form).
fn as_stored(m: &NeuralMaterial, map: &Tensor) -> Result<NeuralMaterial> {
    let weights: HashMap<String, Tensor> = m
        .renderer_vs
        .variables()
        .into_iter()
        .map(|(k, t)| (k, t.detach().to_kind(Kind::Half).to_kind(Kind::Float)))
        .collect();
    NeuralMaterial::from_parts(map.to_device(m.device()), m.input_photo.shallow_clone(), &m.config, &weights, m.meta.clone())
}

/// What was embedded and how far it is from the f32 material.
#[derive(Clone, Debug)]
pub struct ViewerReport {
    pub encoding: MapEncoding,
    /// Mean and max display-level error (of 255) of the stored material
    /// against the f32 one over [`check_configs`].
    pub mean_error: f64,
    pub max_error: f64,
    /// Max error of the 8-bit map when it was tried and refused (auto).
    pub rejected_u8_max_error: Option<f64>,
    /// Bytes of the page.
    pub bytes: usize,
}

impl ViewerReport {
    /// One line for the terminal.
    pub fn summary(&self) -> String {
        let enc = match self.encoding {
            MapEncoding::F16 => "16-bit floats",
            MapEncoding::U8 => "8 bits per channel with a per-channel scale",
        };
        let refused = self.rejected_u8_max_error.map(|e| format!("; 8 bits would be off by up to {e:.2} levels")).unwrap_or_default();
        format!(
            "neural map stored as {enc}, weights as 16-bit floats: against the f32 material, display error mean {:.3} / max {:.2} levels of 255 over {} views{refused}",
            self.mean_error,
            self.max_error,
            check_configs().len()
        )
    }
}

/// Settings of the page.
#[derive(Clone, Debug)]
pub struct ViewerOptions {
    pub map_bits: MapBits,
    /// Light and camera the page opens with (the URL fragment overrides them).
    pub initial: LightView,
    /// File the page's `flashmat relight` command names.
    pub relight_input: String,
}

/// Base64 (standard alphabet, padded).
pub fn base64(bytes: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut s = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for ch in bytes.chunks(3) {
        let b = [ch[0], *ch.get(1).unwrap_or(&0), *ch.get(2).unwrap_or(&0)];
        let n = (b[0] as u32) << 16 | (b[1] as u32) << 8 | b[2] as u32;
        for i in 0..4 {
            if i <= ch.len() {
                s.push(A[(n >> (18 - 6 * i) & 63) as usize] as char);
            } else {
                s.push('=');
            }
        }
    }
    s
}

fn u16_bytes(v: &[u16]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Text safe inside `<script>` and HTML: `<`, `>` and `&` escaped as JSON
/// unicode escapes (valid in the JSON string values they appear in).
fn script_safe(json: &str) -> String {
    json.replace('<', "\\u003c").replace('>', "\\u003e").replace('&', "\\u0026")
}

fn html_escape(s: &str) -> String {
    s.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;").replace('"', "&quot;")
}

/// Builds the page for a material. Returns the HTML and the report (its
/// `bytes` is the page's size).
pub fn build_page(m: &NeuralMaterial, opts: &ViewerOptions) -> Result<(String, ViewerReport)> {
    let (h, w) = m.size();
    let c = m.config.neural_channels as usize;
    let weights = pack_weights(m)?;
    let configs = check_configs();
    let reference = m.render(&configs).context("rendering the f32 material for the encoding check")?;
    let err_of = |map: &Tensor| -> Result<(f64, f64)> { Ok(display_error(&reference, &as_stored(m, map)?.render(&configs)?)) };
    let f16_map = || m.neural_map.to_kind(Kind::Half).to_kind(Kind::Float);
    let (encoding, (mean_error, max_error), rejected, map_b64, map_meta) = match opts.map_bits {
        MapBits::Sixteen => {
            let e = err_of(&f16_map())?;
            (MapEncoding::F16, e, None, base64(&u16_bytes(&pack_map_f16(&m.neural_map)?)), None)
        }
        MapBits::Eight | MapBits::Auto => {
            let q = pack_map_u8(&m.neural_map)?;
            let e = err_of(&q.decoded)?;
            if opts.map_bits == MapBits::Eight || e.1 < 1.0 {
                (MapEncoding::U8, e, None, base64(&q.data), Some((q.offset, q.scale)))
            } else {
                let e16 = err_of(&f16_map())?;
                (MapEncoding::F16, e16, Some(e.1), base64(&u16_bytes(&pack_map_f16(&m.neural_map)?)), None)
            }
        }
    };
    let photo: Vec<f32> = Vec::try_from(m.input_photo.to_device(tch::Device::Cpu).contiguous().view([-1]))?;
    // [3, H, W] -> [H, W, 3] f16.
    let mut photo16 = vec![0u16; 3 * h * w];
    for ch in 0..3 {
        for p in 0..h * w {
            photo16[p * 3 + ch] = to_f16(photo[ch * h * w + p].clamp(0.0, 65504.0))?;
        }
    }
    let layers: Vec<serde_json::Value> = weights
        .layers
        .iter()
        .map(|l| serde_json::json!({"name": l.name, "out": l.out, "in": l.inp, "outPad": l.out_pad, "inPad": l.in_pad, "row": l.row, "slope": l.slope}))
        .collect();
    let (offset, scale) = map_meta.unwrap_or_default();
    let meta = serde_json::json!({
        "format": VIEWER_FORMAT,
        "version": VIEWER_VERSION,
        "source": m.meta.source,
        "modelId": m.meta.model_id,
        "preset": m.config.name,
        "channels": c,
        "frequencies": m.config.enc_frequencies,
        "encOut": m.config.enc_out,
        "width": w,
        "height": h,
        "identity": NeuralMaterial::identity_config().view,
        "light": opts.initial.light,
        "view": opts.initial.view,
        "relightInput": opts.relight_input,
        "layers": layers,
        "weightTexture": [weights.width, weights.height],
        "map": {"bits": if encoding == MapEncoding::U8 { 8 } else { 16 }, "offset": offset, "scale": scale},
        "check": {"meanError": mean_error, "maxError": max_error},
    });
    let data = format!(
        "<script type=\"application/json\" id=\"flashmat-meta\">{}</script>\n<script type=\"text/plain\" id=\"flashmat-weights\">{}</script>\n<script type=\"text/plain\" id=\"flashmat-map\">{}</script>\n<script type=\"text/plain\" id=\"flashmat-photo\">{}</script>",
        script_safe(&meta.to_string()),
        base64(&u16_bytes(&weights.data)),
        map_b64,
        base64(&u16_bytes(&photo16)),
    );
    let title = html_escape(&format!("{} - flashmat neural material", m.meta.source));
    let mut page = PAGE.replace("{{TITLE}}", &title);
    for (key, value) in [("{{LAYER_SHADER}}", LAYER_SHADER), ("{{DISPLAY_SHADER}}", DISPLAY_SHADER), ("{{SCRIPT}}", SCRIPT)] {
        ensure!(page.contains(key), "viewer template lacks {key}");
        page = page.replacen(key, value, 1);
    }
    // Last: the data may contain anything that looks like a placeholder.
    ensure!(page.contains("{{DATA}}"), "viewer template lacks {{DATA}}");
    let page = page.replacen("{{DATA}}", &data, 1);
    let report = ViewerReport { encoding, mean_error, max_error, rejected_u8_max_error: rejected, bytes: page.len() };
    Ok((page, report))
}

/// Builds the page and writes it atomically (no file on error).
pub fn write_page(m: &NeuralMaterial, path: &std::path::Path, opts: &ViewerOptions) -> Result<ViewerReport> {
    let (page, report) = build_page(m, opts)?;
    crate::io::atomic_write_bytes(path, page.as_bytes())?;
    Ok(report)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::infer::nmat::tests::random_material;

    #[test]
    fn base64_matches_known_values() {
        assert_eq!(base64(b""), "");
        assert_eq!(base64(b"f"), "Zg==");
        assert_eq!(base64(b"fo"), "Zm8=");
        assert_eq!(base64(b"foo"), "Zm9v");
        assert_eq!(base64(b"foobar"), "Zm9vYmFy");
        assert_eq!(base64(&[0xff, 0xfe, 0x00, 0x3f]), "//4APw==");
    }

    #[test]
    fn weights_are_padded_and_placed() {
        let m = random_material(7, 8); // tiny: C 16, F 16, enc 32 -> 8, render 16 x5 -> 8 -> 3
        let p = pack_weights(&m).unwrap();
        let names: Vec<&str> = p.layers.iter().map(|l| l.name.as_str()).collect();
        assert_eq!(names, ["nd_enc.0", "nd_enc.1", "nd_enc.2", "m_render.0", "m_render.1", "m_render.2", "m_render.3", "m_render.4", "m_render.5", "m_render.6"]);
        let l0 = &p.layers[0];
        assert_eq!((l0.out, l0.inp, l0.out_pad, l0.in_pad, l0.row), (32, 297, 32, 300, 0));
        assert_eq!(p.width, 75);
        let last = p.layers.last().unwrap();
        assert_eq!((last.out, last.out_pad, last.slope), (3, 4, RENDER_FINAL_SLOPE));
        assert_eq!(p.layers[2].slope, 1.0);
        assert_eq!(p.layers[3].slope, 1.0);
        assert_eq!(p.layers[4].slope, RENDER_SLOPE);
        assert_eq!(p.height, 32 + 32 + 8 + 16 * 5 + 8 + 4);
        assert_eq!(p.data.len(), p.height * p.width * 4);
        let get = |row: usize, col: usize| half::f16::from_bits(p.data[row * p.width * 4 + col]).to_f32();
        // ND_enc 0, element [5, 296]; padding columns 297..300 are zero.
        let w0 = &m.renderer.nd_enc.layers[0];
        assert_eq!(get(5, 296), half::f16::from_f32(w0.double_value(&[5, 296]) as f32).to_f32());
        assert!((297..300).all(|c| get(5, c) == 0.0));
        // M_render 0 [out 16, in 16 + 8]: its code columns start at ceil4(16) = 16, and row 2 of it.
        let m0 = &m.renderer.m_render.layers[0];
        let r0 = p.layers[3].row;
        assert_eq!(get(r0 + 2, 16 + 3), half::f16::from_f32(m0.double_value(&[2, 19]) as f32).to_f32());
        // The last layer's padding row (3) is zero.
        assert!((0..p.width * 4).all(|c| get(last.row + 3, c) == 0.0));
    }

    #[test]
    fn maps_go_to_rgba_layers() {
        // 6 channels -> 2 layers, the second half empty.
        let map = Tensor::arange(6 * 2 * 3, (Kind::Float, tch::Device::Cpu)).view([6, 2, 3]);
        let f = pack_map_f16(&map).unwrap();
        assert_eq!(f.len(), 2 * 2 * 3 * 4);
        let v = |i: usize| half::f16::from_bits(f[i]).to_f32();
        // Layer 0, pixel (row 1, col 2) = p 5: channels 0..3 = 5, 11, 17, 23.
        assert_eq!([v(20), v(21), v(22), v(23)], [5.0, 11.0, 17.0, 23.0]);
        // Layer 1, pixel 0: channels 4, 5, then padding.
        assert_eq!([v(24), v(25), v(26), v(27)], [24.0, 30.0, 0.0, 0.0]);
        assert!(pack_map_f16(&(map * 1e5)).unwrap_err().to_string().contains("f16"));
    }

    #[test]
    fn u8_map_round_trips_within_half_a_step() {
        tch::manual_seed(3);
        let map = Tensor::randn([5, 7, 9], (Kind::Float, tch::Device::Cpu)) * 3.0;
        let q = pack_map_u8(&map).unwrap();
        assert_eq!(q.offset.len(), 5);
        let step = Tensor::from_slice(&q.scale).view([5, 1, 1]) / 255.0;
        let err = ((&q.decoded - &map).abs() / step).max().double_value(&[]);
        assert!(err <= 0.5 + 1e-3, "{err}");
        // The extremes of each channel are exact codes 0 and 255.
        assert!(q.data.contains(&0) && q.data.contains(&255));
        let mins = map.amin([1i64, 2].as_slice(), false);
        assert!((Tensor::from_slice(&q.offset) - mins).abs().max().double_value(&[]) < 1e-6);
    }

    #[test]
    fn page_embeds_everything_and_reports_the_error() {
        let m = random_material(9, 16);
        let opts = ViewerOptions { map_bits: MapBits::Sixteen, initial: NeuralMaterial::identity_config(), relight_input: "m</script>.nmat".into() };
        let (page, report) = build_page(&m, &opts).unwrap();
        assert_eq!(report.encoding, MapEncoding::F16);
        assert!(report.max_error < 1.0 && report.mean_error <= report.max_error, "{report:?}");
        assert_eq!(report.bytes, page.len());
        assert!(!page.contains("{{"), "placeholder left in the page");
        assert!(page.contains("#version 300 es") && page.contains("getContext(\"webgl2\""));
        // The file name cannot close the script element.
        assert_eq!(page.matches("</script>").count(), page.matches("<script").count());
        assert!(page.contains("m\\u003c/script\\u003e.nmat"));
        // Map: 16 channels = 4 layers of 16 x 16 RGBA f16 = 8192 bytes -> base64 of 10924 chars.
        let map_block = page.split("id=\"flashmat-map\">").nth(1).unwrap().split('<').next().unwrap();
        assert_eq!(map_block.len(), 8192usize.div_ceil(3) * 4);
        let (_, r8) = build_page(&m, &ViewerOptions { map_bits: MapBits::Eight, ..opts.clone() }).unwrap();
        assert_eq!(r8.encoding, MapEncoding::U8);
        assert!(r8.bytes < report.bytes);
        assert!(r8.max_error >= report.max_error, "8 bits ({}) closer than f16 ({})?", r8.max_error, report.max_error);
        assert!(report.summary().contains("16-bit floats"));
    }
}
