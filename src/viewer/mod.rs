//! `flashmat view`: a neural material as one self-contained HTML page that
//! re-renders it live in the browser (WebGL2), with the light under the
//! mouse. See docs/VIEWER.md.
//!
//! The page embeds (base64, no network):
//! - the ND_enc + M_render weights, layer after layer, each `[out, in]`
//!   matrix padded to multiples of 4 in both dimensions and row-major
//!   ([`pack_weights`]); f16, or f32 where f16 would move the render by
//!   half a display level or more ([`Precision`]);
//! - the neural map as a texture array of ceil(C/4) RGBA layers, 8-bit
//!   with a per-channel scale and offset, f16 or f32: the smallest that
//!   keeps the render within one display level of the f32 material;
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

/// How numbers are stored in the page.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Precision {
    /// 8 bits per value, value = offset[c] + scale[c] * q / 255 per channel (maps only).
    U8,
    /// IEEE half floats (2 bytes per value).
    F16,
    /// IEEE single floats, exact.
    F32,
}

impl Precision {
    pub fn bits(self) -> u32 {
        match self {
            Precision::U8 => 8,
            Precision::F16 => 16,
            Precision::F32 => 32,
        }
    }
}

/// What `--map-bits` / `--weight-bits` ask for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Bits {
    /// The smallest storage whose render stays within the display-level budget on the check views.
    Auto,
    #[value(name = "8")]
    Eight,
    #[value(name = "16")]
    Sixteen,
    #[value(name = "32")]
    ThirtyTwo,
}

impl Bits {
    fn fixed(self) -> Option<Precision> {
        match self {
            Bits::Auto => None,
            Bits::Eight => Some(Precision::U8),
            Bits::Sixteen => Some(Precision::F16),
            Bits::ThirtyTwo => Some(Precision::F32),
        }
    }
}

/// Largest display-level error (of 255) on the check views that `auto`
/// accepts: the map's storage and the weights' may each take up to
/// [`WEIGHT_ERROR_BUDGET`] of it.
pub const ERROR_BUDGET: f64 = 1.0;
pub const WEIGHT_ERROR_BUDGET: f64 = 0.5;

/// One network layer in the packed weights.
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
    /// Index of the layer's first value in [`PackedWeights::data`].
    pub offset: usize,
    /// LeakyReLU slope after the layer (1 = no activation).
    pub slope: f64,
}

/// ND_enc + M_render as one array of values.
#[derive(Clone, Debug)]
pub struct PackedWeights {
    /// The layers one after the other, each `[out_pad, in_pad]` row-major
    /// (zero padding), from its `offset`.
    pub data: Vec<f32>,
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
    let f = m.config.enc_frequencies as usize;
    ensure!(f <= MAX_FREQUENCIES, "the viewer supports up to {MAX_FREQUENCIES} encoding frequencies, this material has {f}");
    ensure!(!m.config.half_angle_feature, "the viewer does not draw renderers that read the log half-angle feature (model {}, issue 48) yet", m.config.name);
    let mut layers = Vec::new();
    let mut mats = Vec::new();
    let mut offset = 0;
    for (name, w, slope) in layer_matrices(m) {
        let s = w.size();
        ensure!(s.len() == 2, "layer {name} must be a matrix, got shape {s:?}");
        let (out, inp) = (s[0] as usize, s[1] as usize);
        let in_pad = if name == "nd_enc.0" {
            ensure!(inp == m.config.encoding_width() as usize, "layer nd_enc.0 has {inp} inputs, expected {}", m.config.encoding_width());
            encoding_columns(m.config.enc_frequencies as usize)
        } else if name == "m_render.0" {
            ensure!(inp > c, "layer m_render.0 has {inp} inputs, fewer than the {c} neural channels");
            ceil4(c) + ceil4(inp - c)
        } else {
            ceil4(inp)
        };
        let out_pad = ceil4(out);
        layers.push(PackedLayer { name, out, inp, out_pad, in_pad, offset, slope });
        offset += out_pad * in_pad;
        mats.push(w);
    }
    let mut data = vec![0f32; offset];
    for (l, w) in layers.iter().zip(&mats) {
        let vals: Vec<f32> = Vec::try_from(w.contiguous().view([-1]))?;
        for o in 0..l.out {
            for i in 0..l.inp {
                let col = match l.name.as_str() {
                    "nd_enc.0" => encoding_column(i, m.config.enc_frequencies as usize),
                    "m_render.0" if i >= c => ceil4(c) + (i - c),
                    _ => i,
                };
                data[l.offset + o * l.in_pad + col] = vals[o * l.inp + i];
            }
        }
    }
    Ok(PackedWeights { data, layers })
}

/// Largest encoding frequency count the shader supports (phases scale by `1 << k` in 32-bit ints).
pub const MAX_FREQUENCIES: usize = 28;

/// Padded input width of ND_enc's first layer in the shader's order:
/// 12 + 72 ceil(F / 4) (see [`encoding_column`]).
pub fn encoding_columns(frequencies: usize) -> usize {
    12 + 72 * frequencies.div_ceil(4)
}

/// Column of encoding channel `n` (docs/NMAT.md order: v (9), sin k-major
/// (9 F), cos (9 F)) in the shader's order, which computes sin and cos of
/// four phases at a time: V0 = (wi, wo.x), V1 = (wo.y, wo.z, h.x, h.y),
/// (h.z, 0, 0, 0); then per block of four frequencies k = 4b .. 4b+3, for
/// each k: sin(phase(2^k V0)), cos(..), sin(phase(2^k V1)), cos(..) (16
/// columns), then sin and cos of h.z at the block's four frequencies (8
/// columns). Unused columns (3 after h.z, frequencies past F) stay zero.
pub fn encoding_column(n: usize, frequencies: usize) -> usize {
    if n < 9 {
        return n;
    }
    let j = n - 9;
    let (is_cos, j) = if j >= 9 * frequencies { (true, j - 9 * frequencies) } else { (false, j) };
    let (k, c) = (j / 9, j % 9);
    let base = 12 + 72 * (k / 4);
    let kk = k % 4;
    let cos = if is_cos { 4 } else { 0 };
    match c {
        0..=3 => base + 16 * kk + cos + c,
        4..=7 => base + 16 * kk + 8 + cos + (c - 4),
        _ => base + 64 + cos + kk,
    }
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

/// A neural map `[C, H, W]` in texture-array order (f32 values).
pub fn map_layers(map: &Tensor) -> Result<Vec<f32>> {
    let s = map.size();
    ensure!(s.len() == 3, "neural map must be [C, H, W], got {s:?}");
    let vals: Vec<f32> = Vec::try_from(map.to_kind(Kind::Float).to_device(tch::Device::Cpu).contiguous().view([-1]))?;
    Ok(to_layers(&vals, s[0] as usize, s[1] as usize, s[2] as usize))
}

/// Little-endian bytes of values as f16 (`what` names them in the error
/// for values beyond the f16 range) or f32.
pub fn float_bytes(values: &[f32], precision: Precision, what: &str) -> Result<Vec<u8>> {
    match precision {
        Precision::F32 => Ok(values.iter().flat_map(|v| v.to_le_bytes()).collect()),
        Precision::F16 => {
            let bits = values.iter().map(|&v| to_f16(v)).collect::<Result<Vec<u16>>>().with_context(|| format!("{what} cannot be stored as f16"))?;
            Ok(u16_bytes(&bits))
        }
        Precision::U8 => bail!("{what}: 8-bit storage needs a per-channel scale"),
    }
}

/// Values rounded through f16 (`Kind::Half`) and back; f32 unchanged.
fn rounded(t: &Tensor, precision: Precision) -> Tensor {
    match precision {
        Precision::F16 => t.to_kind(Kind::Half).to_kind(Kind::Float),
        _ => t.to_kind(Kind::Float),
    }
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
/// (mean, max) of |display(a) - display(b)| x 255 with display the sRGB
/// curve of clamp(R, 0, 1), the PNG transform of `flashmat relight`
/// ([`crate::spaces::linear_to_photo`]).
pub fn display_error(a: &Tensor, b: &Tensor) -> (f64, f64) {
    let d = (crate::spaces::linear_to_photo(a) - crate::spaces::linear_to_photo(b)).abs() * 255.0;
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

/// The material as the page evaluates it: weights in `weights` precision
/// and the given map `[C, H, W]` (already decoded from its stored form).
fn as_stored(m: &NeuralMaterial, map: &Tensor, weights: Precision) -> Result<NeuralMaterial> {
    let weights: HashMap<String, Tensor> =
        m.renderer_vs.variables().into_iter().map(|(k, t)| (k, rounded(&t.detach(), weights))).collect();
    NeuralMaterial::from_parts(map.to_device(m.device()), m.input_photo.shallow_clone(), &m.config, &weights, m.meta.clone())
}

/// What was embedded and how far it is from the f32 material.
#[derive(Clone, Debug)]
pub struct ViewerReport {
    pub map: Precision,
    pub weights: Precision,
    /// Mean and max display-level error (of 255) of the stored material
    /// against the f32 one over [`check_configs`].
    pub mean_error: f64,
    pub max_error: f64,
    /// Smaller storages `auto` tried and refused, with their max error.
    pub refused: Vec<(&'static str, Precision, f64)>,
    /// Bytes of the page.
    pub bytes: usize,
}

fn describe(p: Precision) -> &'static str {
    match p {
        Precision::U8 => "8 bits with a per-channel scale",
        Precision::F16 => "16-bit floats",
        Precision::F32 => "32-bit floats",
    }
}

impl ViewerReport {
    /// One line for the terminal.
    pub fn summary(&self) -> String {
        let refused: String =
            self.refused.iter().map(|(what, p, e)| format!("; {what} in {} bits would be off by up to {e:.2} levels", p.bits())).collect();
        format!(
            "neural map stored as {}, weights as {}: against the f32 material, display error mean {:.3} / max {:.2} levels of 255 over {} views{refused}",
            describe(self.map),
            describe(self.weights),
            self.mean_error,
            self.max_error,
            check_configs().len()
        )
    }
}

/// Settings of the page.
#[derive(Clone, Debug)]
pub struct ViewerOptions {
    pub map_bits: Bits,
    pub weight_bits: Bits,
    /// Light and camera the page opens with (the URL fragment overrides them).
    pub initial: LightView,
    /// File the page's `flashmat relight` command names.
    pub relight_input: String,
}

/// The stored map's precision and the decoded map the page will see
/// (u8 also returns its codes).
struct StoredMap {
    precision: Precision,
    u8: Option<U8Map>,
}

impl StoredMap {
    fn new(m: &NeuralMaterial, precision: Precision) -> Result<Self> {
        let u8 = if precision == Precision::U8 { Some(pack_map_u8(&m.neural_map)?) } else { None };
        Ok(Self { precision, u8 })
    }

    fn decoded(&self, m: &NeuralMaterial) -> Tensor {
        match &self.u8 {
            Some(q) => q.decoded.shallow_clone(),
            None => rounded(&m.neural_map, self.precision),
        }
    }
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
    let err_of = |map: &Tensor, w: Precision| -> Result<(f64, f64)> {
        Ok(display_error(&reference, &as_stored(m, map, w)?.render(&configs)?))
    };
    let mut refused = Vec::new();
    let weight_precision = match opts.weight_bits {
        Bits::Auto => {
            let e = err_of(&m.neural_map, Precision::F16)?;
            if e.1 < WEIGHT_ERROR_BUDGET {
                Precision::F16
            } else {
                refused.push(("weights", Precision::F16, e.1));
                Precision::F32
            }
        }
        Bits::Eight => bail!("weights are stored in 16 or 32 bits (--weight-bits 16|32|auto)"),
        b => b.fixed().expect("not auto"),
    };
    let (stored, (mean_error, max_error)) = match opts.map_bits.fixed() {
        Some(p) => {
            let sm = StoredMap::new(m, p)?;
            let e = err_of(&sm.decoded(m), weight_precision)?;
            (sm, e)
        }
        None => {
            let mut chosen = None;
            for p in [Precision::U8, Precision::F16, Precision::F32] {
                let sm = StoredMap::new(m, p)?;
                // f16 cannot hold values beyond 65504: the next precision.
                if p == Precision::F16 && !crate::image::all_finite(&sm.decoded(m)) {
                    continue;
                }
                let e = err_of(&sm.decoded(m), weight_precision)?;
                if e.1 < ERROR_BUDGET || p == Precision::F32 {
                    chosen = Some((sm, e));
                    break;
                }
                refused.push(("the map", p, e.1));
            }
            chosen.expect("f32 is always accepted")
        }
    };
    let (map_b64, offset, scale) = match &stored.u8 {
        Some(q) => (base64(&q.data), q.offset.clone(), q.scale.clone()),
        None => (base64(&float_bytes(&map_layers(&m.neural_map)?, stored.precision, "the neural map")?), Vec::new(), Vec::new()),
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
        .map(|l| serde_json::json!({"name": l.name, "out": l.out, "in": l.inp, "outPad": l.out_pad, "inPad": l.in_pad, "offset": l.offset, "slope": l.slope}))
        .collect();
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
        "gain": m.meta.gain,
        "identityCheck": crate::infer::identity_check(m)?,
        "identity": NeuralMaterial::identity_config().view,
        "light": opts.initial.light,
        "view": opts.initial.view,
        "relightInput": opts.relight_input,
        "layers": layers,
        "weightBits": weight_precision.bits(),
        "map": {"bits": stored.precision.bits(), "offset": offset, "scale": scale},
        "check": {"meanError": mean_error, "maxError": max_error},
    });
    let data = format!(
        "<script type=\"application/json\" id=\"flashmat-meta\">{}</script>\n<script type=\"text/plain\" id=\"flashmat-weights\">{}</script>\n<script type=\"text/plain\" id=\"flashmat-map\">{}</script>\n<script type=\"text/plain\" id=\"flashmat-photo\">{}</script>",
        script_safe(&meta.to_string()),
        base64(&float_bytes(&weights.data, weight_precision, "the weights")?),
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
    let report = ViewerReport { map: stored.precision, weights: weight_precision, mean_error, max_error, refused, bytes: page.len() };
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
        assert_eq!((l0.out, l0.inp, l0.out_pad, l0.in_pad, l0.offset), (32, 297, 32, 300, 0));
        assert_eq!(p.layers[1].offset, 32 * 300);
        let last = p.layers.last().unwrap();
        assert_eq!((last.out, last.out_pad, last.slope), (3, 4, RENDER_FINAL_SLOPE));
        assert_eq!(p.layers[2].slope, 1.0);
        assert_eq!(p.layers[3].slope, 1.0);
        assert_eq!(p.layers[4].slope, RENDER_SLOPE);
        // nd_enc: 32 x 300, 32 x 32, 8 x 32; m_render: 16 x 24, 4 x 16 x 16, 8 x 16, 4 x 8.
        assert_eq!(p.data.len(), 32 * 300 + 32 * 32 + 8 * 32 + 16 * 24 + 4 * 16 * 16 + 8 * 16 + 4 * 8);
        let get = |l: usize, row: usize, col: usize| p.data[p.layers[l].offset + row * p.layers[l].in_pad + col];
        let at = |t: &Tensor, o: i64, i: i64| t.double_value(&[o, i]) as f32;
        // ND_enc 0, element [5, 296] (cos of h.z at k = 15): column 12 + 72 * 3 + 68 + 3.
        let w0 = &m.renderer.nd_enc.layers[0];
        assert_eq!(get(0, 5, 299), at(w0, 5, 296));
        assert_eq!(get(0, 5, 4), at(w0, 5, 4));
        assert!((9..12).all(|c| get(0, 5, c) == 0.0));
        // M_render 0 [out 16, in 16 + 8]: its code columns start at ceil4(16) = 16, and row 2 of it.
        let m0 = &m.renderer.m_render.layers[0];
        assert_eq!(get(3, 2, 16 + 3), at(m0, 2, 19));
        // Every weight is placed once: the table sums to the weights' sum.
        let total: f64 = p.data.iter().map(|&v| v as f64).sum();
        let expect: f64 = m.renderer_vs.variables().values().map(|t| t.sum(Kind::Double).double_value(&[])).sum();
        assert!((total - expect).abs() < 1e-3, "{total} vs {expect}");
        // The last layer's padding row (3) is zero.
        assert!((0..last.in_pad).all(|c| get(9, 3, c) == 0.0));
    }

    #[test]
    fn encoding_columns_are_a_permutation_into_the_padded_layout() {
        for f in [1usize, 4, 5, 16] {
            let width = encoding_columns(f);
            let cols: Vec<usize> = (0..9 + 18 * f).map(|n| encoding_column(n, f)).collect();
            let mut sorted = cols.clone();
            sorted.sort();
            sorted.dedup();
            assert_eq!(sorted.len(), cols.len(), "F = {f}: two channels share a column");
            assert!(cols.iter().all(|&c| c < width && !(9..12).contains(&c)), "F = {f}");
        }
        assert_eq!(encoding_columns(16), 300);
        // sin(2^0 pi wi.x) (channel 9) -> 12; cos of it (channel 9 + 144) -> 16;
        // sin(2^1 pi wo.y) (channel 9 + 9 + 4) -> 12 + 16 + 8; sin(2^5 pi h.z) -> 12 + 72 + 64 + 1.
        assert_eq!(encoding_column(9, 16), 12);
        assert_eq!(encoding_column(9 + 144, 16), 16);
        assert_eq!(encoding_column(9 + 9 + 4, 16), 36);
        assert_eq!(encoding_column(9 + 45 + 8, 16), 149);
    }

    #[test]
    fn maps_go_to_rgba_layers() {
        // 6 channels -> 2 layers, the second half empty.
        let map = Tensor::arange(6 * 2 * 3, (Kind::Float, tch::Device::Cpu)).view([6, 2, 3]);
        let f = map_layers(&map).unwrap();
        assert_eq!(f.len(), 2 * 2 * 3 * 4);
        let v = |i: usize| f[i];
        // Layer 0, pixel (row 1, col 2) = p 5: channels 0..3 = 5, 11, 17, 23.
        assert_eq!([v(20), v(21), v(22), v(23)], [5.0, 11.0, 17.0, 23.0]);
        // Layer 1, pixel 0: channels 4, 5, then padding.
        assert_eq!([v(24), v(25), v(26), v(27)], [24.0, 30.0, 0.0, 0.0]);
        let b = float_bytes(&f, Precision::F16, "the map").unwrap();
        assert_eq!(half::f16::from_bits(u16::from_le_bytes([b[46], b[47]])).to_f32(), 23.0);
        assert_eq!(float_bytes(&f, Precision::F32, "the map").unwrap()[96..100], 24f32.to_le_bytes());
        let e = float_bytes(&[1e5], Precision::F16, "the map").unwrap_err().to_string();
        assert!(e.contains("the map cannot be stored as f16"), "{e}");
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
        let opts = ViewerOptions {
            map_bits: Bits::Sixteen,
            weight_bits: Bits::Sixteen,
            initial: NeuralMaterial::identity_config(),
            relight_input: "m</script>.nmat".into(),
        };
        let (page, report) = build_page(&m, &opts).unwrap();
        assert_eq!((report.map, report.weights), (Precision::F16, Precision::F16));
        assert!(report.mean_error <= report.max_error, "{report:?}");
        assert_eq!(report.bytes, page.len());
        assert!(!page.contains("{{"), "placeholder left in the page");
        assert!(page.contains("#version 300 es") && page.contains("getContext(\"webgl2\""));
        // The file name cannot close the script element.
        assert_eq!(page.matches("</script>").count(), page.matches("<script").count());
        assert!(page.contains("m\\u003c/script\\u003e.nmat"));
        let block = |page: &str, id: &str| page.split(&format!("id=\"{id}\">")).nth(1).unwrap().split('<').next().unwrap().len();
        // Map: 16 channels = 4 layers of 16 x 16 RGBA f16 = 8192 bytes -> base64 of 10924 chars.
        assert_eq!(block(&page, "flashmat-map"), 8192usize.div_ceil(3) * 4);
        // Exact storage: f32 map and weights, no error at all.
        let exact = ViewerOptions { map_bits: Bits::ThirtyTwo, weight_bits: Bits::ThirtyTwo, ..opts.clone() };
        let (page32, r32) = build_page(&m, &exact).unwrap();
        assert_eq!((r32.max_error, r32.map, r32.weights), (0.0, Precision::F32, Precision::F32));
        assert_eq!(block(&page32, "flashmat-map"), 16384usize.div_ceil(3) * 4);
        let n = pack_weights(&m).unwrap().data.len();
        assert_eq!(block(&page, "flashmat-weights"), (2 * n).div_ceil(3) * 4);
        assert_eq!(block(&page32, "flashmat-weights"), (4 * n).div_ceil(3) * 4);
        let (_, r8) = build_page(&m, &ViewerOptions { map_bits: Bits::Eight, ..opts.clone() }).unwrap();
        assert_eq!(r8.map, Precision::U8);
        assert!(r8.bytes < report.bytes);
        assert!(r8.max_error >= report.max_error, "8 bits ({}) closer than f16 ({})?", r8.max_error, report.max_error);
        assert!(report.summary().contains("16-bit floats"));
        // Auto keeps the render within the budget, refusing what does not.
        let (_, ra) = build_page(&m, &ViewerOptions { map_bits: Bits::Auto, weight_bits: Bits::Auto, ..opts.clone() }).unwrap();
        assert!(ra.max_error < ERROR_BUDGET, "{ra:?}");
        assert!(ra.refused.iter().all(|r| r.2 >= WEIGHT_ERROR_BUDGET), "{ra:?}");
        assert!(ra.map == Precision::U8 || ra.refused.iter().any(|r| r.0 == "the map" && r.1 == Precision::U8), "{ra:?}");
        assert!(build_page(&m, &ViewerOptions { weight_bits: Bits::Eight, ..opts }).unwrap_err().to_string().contains("16 or 32 bits"));
    }
}
