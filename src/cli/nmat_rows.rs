//! `flashmat nmat-rows`: reference rows of a neural material for other
//! implementations of the .nmat renderer (the Mitsuba 3 plugin in
//! python/flashmat/mitsuba checks itself against them). Each row is one
//! pixel's parameters, a light direction wi and a view direction wo (unit,
//! upper hemisphere, material frame) and flashmat's own M_render output
//! ln(1 + R), computed by `NeuralRenderer::forward_rows`.

use super::prepare_output;
use flashmat::infer::NeuralMaterial;
use anyhow::{bail, ensure, Result};
use clap::Args;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use std::path::PathBuf;
use tch::{Device, Kind, Tensor};

#[derive(Args, Debug)]
pub struct NmatRowsArgs {
    /// Neural material (.nmat).
    pub material: PathBuf,
    /// Number of rows (random pixel, random wi and wo with an exactly computable half vector).
    #[arg(long, default_value_t = 64)]
    pub count: usize,
    /// Random seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output JSON file.
    #[arg(short, long)]
    pub output: PathBuf,
}

/// Integer (a, b, c, d) with a^2 + b^2 + c^2 = d^2, 0 < d < 32.
fn quadruples() -> Vec<[i64; 4]> {
    let mut q = Vec::new();
    for a in 0..32i64 {
        for b in 0..32i64 {
            for c in 1..32i64 {
                let n = a * a + b * b + c * c;
                let d = (n as f64).sqrt().round() as i64;
                if d * d == n && d < 32 && (a > 0 || b > 0) {
                    q.push([a, b, c, d]);
                }
            }
        }
    }
    q
}

/// A pair of unit directions (f32, upper hemisphere, z >= 0.02) whose f32
/// sum s = wi + wo is exact with |s| exactly representable: s = (a, b, c) 2^-e
/// for a Pythagorean quadruple. Then every implementation computes the same
/// half vector s / |s| (f32 sum, squares and square root all exact; one
/// correctly rounded division), whatever its sqrt or summation order. The
/// encoding multiplies h by up to 2^15 pi, so one ulp of h is ~1e-2 rad of
/// phase: rows with an inexact half vector cannot be compared to 1e-4.
fn robust_pair(rng: &mut Pcg64, quads: &[[i64; 4]]) -> ([f32; 3], [f32; 3]) {
    loop {
        let [a, b, c, d] = quads[rng.random_range(0..quads.len())];
        let (a, b) = (if rng.random() { -a } else { a }, if rng.random() { -b } else { b });
        let (x, y) = if rng.random() { (a, b) } else { (b, a) };
        let e = rng.random_range(0..6);
        let scale = (2.0f64).powi(-e);
        let len = d as f64 * scale;
        if !(0.3..1.9).contains(&len) {
            continue;
        }
        let s = [x as f64 * scale, y as f64 * scale, c as f64 * scale];
        // A random unit vector orthogonal to s.
        let r: [f64; 3] = [rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)];
        let k = (r[0] * s[0] + r[1] * s[1] + r[2] * s[2]) / (len * len);
        let u = [r[0] - k * s[0], r[1] - k * s[1], r[2] - k * s[2]];
        let un = (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt();
        if un < 0.1 {
            continue;
        }
        let t = (1.0 - len * len / 4.0).sqrt() / un;
        let wi: [f32; 3] = std::array::from_fn(|i| (s[i] / 2.0 + t * u[i]) as f32);
        let sf: [f32; 3] = std::array::from_fn(|i| s[i] as f32);
        let wo: [f32; 3] = std::array::from_fn(|i| sf[i] - wi[i]);
        if wi[2] >= 0.02 && wo[2] >= 0.02 && (0..3).all(|i| wi[i] + wo[i] == sf[i]) {
            return (wi, wo);
        }
    }
}

pub fn nmat_rows(a: &NmatRowsArgs) -> Result<()> {
    ensure!(a.count > 0, "--count must be positive");
    flashmat::limits::COUNT.check("--count", a.count as u64)?;
    let mat = NeuralMaterial::load(&a.material, Device::Cpu)?;
    let (h, w) = mat.size();
    let c = mat.config.neural_channels as usize;
    let map = Vec::<f32>::try_from(mat.neural_map.to_kind(Kind::Float).contiguous().view([-1]))?;
    let mut rng = Pcg64::seed_from_u64(a.seed);
    let quads = quadruples();
    let mut pixels = Vec::with_capacity(a.count);
    let (mut params, mut wis, mut wos) = (Vec::new(), Vec::new(), Vec::new());
    for _ in 0..a.count {
        let (i, j) = (rng.random_range(0..h), rng.random_range(0..w));
        pixels.push([i, j]);
        for ch in 0..c {
            params.push(map[(ch * h + i) * w + j]);
        }
        let (wi, wo) = robust_pair(&mut rng, &quads);
        wis.extend(wi);
        wos.extend(wo);
    }
    let r = a.count as i64;
    let p = Tensor::from_slice(&params).view([r, c as i64]);
    let wi = Tensor::from_slice(&wis).view([r, 3]);
    let wo = Tensor::from_slice(&wos).view([r, 3]);
    let out = tch::no_grad(|| mat.renderer.forward_rows(&p, &wi, &wo))?;
    let out = Vec::<f32>::try_from(out.to_kind(Kind::Float).contiguous().view([-1]))?;
    // JSON has no NaN or Inf (serde_json would write null).
    if let Some(k) = out.iter().position(|v| !v.is_finite()) {
        bail!("{}: M_render's output of row {} is {} (weights out of range?)", a.material.display(), k / 3, out[k]);
    }
    let rows: Vec<serde_json::Value> = (0..a.count)
        .map(|k| {
            serde_json::json!({
                "pixel": pixels[k],
                "params": &params[k * c..(k + 1) * c],
                "wi": &wis[k * 3..k * 3 + 3],
                "wo": &wos[k * 3..k * 3 + 3],
                "out": &out[k * 3..k * 3 + 3],
            })
        })
        .collect();
    let doc = serde_json::json!({
        "material": a.material.file_name().map(|s| s.to_string_lossy().into_owned()),
        "model_id": mat.meta.model_id,
        "seed": a.seed,
        "note": "out = ln(1 + R) from flashmat's M_render (f32); wi towards the light, wo towards the camera, material frame; |wi + wo| is exact in f32",
        "rows": rows,
    });
    let out_dir = prepare_output(&a.output)?;
    flashmat::io::atomic_write_bytes(&a.output, serde_json::to_string_pretty(&doc)?.as_bytes())?;
    out_dir.keep();
    eprintln!("wrote {} rows to {}", a.count, a.output.display());
    Ok(())
}
