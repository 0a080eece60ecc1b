//! The shadows experiment (REFERENCE section 8): can per-pixel neural
//! parameters carry shadows, which a per-pixel analytic BRDF cannot?
//!
//! For each material the input photo is its shadowed co-located GGX render.
//! K fixed lights ([`shadow_configs`]: low to medium elevations spread in
//! azimuth, seen from the input camera) give the un-shadowed GGX render U,
//! the visibility V of each pixel (height-field march, [`ShadowOptions`]) and
//! the shadowed reference S = U V. Each method re-renders the K lights from
//! the photo (P) and is scored with
//! - LPIPS(P, S) and LPIPS(P, U) (the paper's protocol: linear, clamped);
//! - RMSE of ln(1 + R) against S;
//! - the shadow contrast recovered, `1 - dark / lit` with
//!   `dark = sum P (1-V) / sum U (1-V)` (how bright the method leaves the
//!   shadowed pixels, relative to the un-shadowed render) and
//!   `lit = sum P V / sum U V` (the same over lit pixels). S scores 1, U
//!   scores 0, and a method that only scales the whole image also scores 0:
//!   only darkening *where the shadows are* counts.
//!
//! The un-shadowed GGX render of the true maps is reported as its own row:
//! it is the best any per-pixel analytic BRDF can do.

use super::methods::{open_methods, Method};
use super::metrics::{mean_ci95, score_renders};
use crate::geometry::{fov_to_distance, LightView, HEMISPHERE_RADIUS, MODEL_FOV_DEG};
use crate::image::Image;
use crate::lpips::Lpips;
use crate::svbrdf::height::shadow_heights;
use crate::svbrdf::shadow::ShadowOptions;
use crate::svbrdf::Svbrdf;
use anyhow::{anyhow, ensure, Result};
use indicatif::{ProgressBar, ProgressStyle};
use std::fmt::Write as _;
use std::path::PathBuf;
use tch::{Device, Kind, Tensor};

/// JPEG quality of the per-material grids (1304 x 2084 pixels each, the
/// largest pictures in the repository): below the other reports' 88 to keep
/// the tree under the GPU jobs' limit; 75 takes a third off each
/// (0.85 -> 0.58 MB) without visible blocking at the grid's cell size.
const SHADOW_GRID_JPEG_QUALITY: u8 = 75;

/// Light elevations the configurations cycle through, in degrees.
pub const SHADOW_ELEVATIONS_DEG: [f64; 4] = [20.0, 30.0, 45.0, 60.0];

/// Name of the un-shadowed GGX row.
pub const GGX_UNSHADOWED: &str = "ggx-unshadowed";

/// Everything `flashmat shadow-eval` needs.
#[derive(Clone, Debug)]
pub struct ShadowEvalOptions {
    /// Model files (flashmat or baseline exports) or `printout`.
    pub models: Vec<String>,
    /// As `flashmat eval`: `procedural-test`, `procedural-test:I` or a folder.
    pub dataset: String,
    pub out: PathBuf,
    pub size: usize,
    pub limit: Option<usize>,
    /// Lights per material.
    pub lights: usize,
    pub shadows: ShadowOptions,
    pub ldr_input: bool,
    /// Grids of this many materials (the most shadowed ones).
    pub grids: usize,
    pub device: Device,
    pub progress: bool,
}

/// K fixed lights on the radius-4 hemisphere: elevations cycle through
/// [`SHADOW_ELEVATIONS_DEG`], azimuths step by 360/K degrees from 15; all
/// seen from the input photo's camera, (0, 0, d) for the 28 degree FOV, so
/// every render lines up with the photo.
pub fn shadow_configs(count: usize) -> Vec<LightView> {
    let view = [0.0, 0.0, fov_to_distance(MODEL_FOV_DEG)];
    (0..count)
        .map(|i| {
            let elevation = SHADOW_ELEVATIONS_DEG[i % SHADOW_ELEVATIONS_DEG.len()].to_radians();
            let azimuth = (15.0 + 360.0 * i as f64 / count as f64).to_radians();
            let light = [
                HEMISPHERE_RADIUS * elevation.cos() * azimuth.cos(),
                HEMISPHERE_RADIUS * elevation.cos() * azimuth.sin(),
                HEMISPHERE_RADIUS * elevation.sin(),
            ];
            LightView { light, view }
        })
        .collect()
}

/// Visibility `[K, 1, H, W]` of the configurations' lights over the
/// material's height field (integrated from the normals when it has none).
pub fn visibility_maps(m: &Svbrdf, configs: &[LightView], options: &ShadowOptions) -> Result<Tensor> {
    let heights = shadow_heights(m)?;
    let lights: Vec<[f64; 3]> = configs.iter().map(|c| c.light).collect();
    let v = crate::svbrdf::cpu::visibility(&heights, &lights, options)?;
    Ok(Tensor::from_slice(&v).view([configs.len() as i64, 1, m.height() as i64, m.width() as i64]))
}

/// `(dark, lit)` brightness ratios of `pred` against the un-shadowed
/// render over shadowed and lit pixels (see the module notes); `None` when
/// the renders hold no shadow (or no lit pixel).
/// pred, unshadowed: `[K, 3, H, W]`; visibility: `[K, 1, H, W]`.
pub fn shadow_ratios(pred: &Tensor, unshadowed: &Tensor, visibility: &Tensor) -> Option<(f64, f64)> {
    let pred = pred.to_device(Device::Cpu).to_kind(Kind::Double).clamp_min(0.0);
    let unshadowed = unshadowed.to_device(Device::Cpu).to_kind(Kind::Double);
    let lit = visibility.to_device(Device::Cpu).to_kind(Kind::Double);
    let dark = lit.ones_like() - &lit;
    let sum = |t: Tensor| t.sum(Kind::Double).double_value(&[]);
    let (u_dark, u_lit) = (sum(&unshadowed * &dark), sum(&unshadowed * &lit));
    // Below this the shadows (or lit areas) carry no measurable light.
    let floor = 1e-6 * (u_dark + u_lit).max(f64::MIN_POSITIVE);
    if u_dark <= floor || u_lit <= floor {
        return None;
    }
    Some((sum(&pred * &dark) / u_dark, sum(&pred * &lit) / u_lit))
}

/// Shadow contrast recovered from the ratios of [`shadow_ratios`]:
/// `1 - dark / lit` (1: the reference's shadows, 0: none).
pub fn contrast_recovered((dark, lit): (f64, f64)) -> f64 {
    if lit <= 0.0 {
        0.0
    } else {
        1.0 - dark / lit
    }
}

/// Scores of one method on one light.
#[derive(Clone, Debug)]
pub struct ShadowRow {
    pub material: String,
    pub light: usize,
    pub method: String,
    pub lpips_shadowed: f64,
    pub lpips_unshadowed: f64,
    pub rmse_log_shadowed: f64,
    /// `None` when this light casts no shadow on the material.
    pub recovered: Option<f64>,
    /// Fraction of the un-shadowed light that the shadows remove.
    pub shadowed_light: f64,
}

/// Scores `pred` (`[K, 3, H, W]`) light by light.
fn score_method(
    lpips: &Lpips,
    material: &str,
    method: &str,
    pred: &Tensor,
    unshadowed: &Tensor,
    shadowed: &Tensor,
    visibility: &Tensor,
) -> Result<Vec<ShadowRow>> {
    let vs_shadowed = score_renders(lpips, pred, shadowed)?;
    let vs_unshadowed = score_renders(lpips, pred, unshadowed)?;
    Ok((0..vs_shadowed.len())
        .map(|k| {
            let one = |t: &Tensor| t.narrow(0, k as i64, 1);
            let (u, v) = (one(unshadowed), one(visibility));
            let total = u.sum(Kind::Double).double_value(&[]);
            let removed = (&u * (v.ones_like() - &v)).sum(Kind::Double).double_value(&[]);
            ShadowRow {
                material: material.to_string(),
                light: k,
                method: method.to_string(),
                lpips_shadowed: vs_shadowed[k].lpips,
                lpips_unshadowed: vs_unshadowed[k].lpips,
                rmse_log_shadowed: vs_shadowed[k].rmse_log,
                recovered: shadow_ratios(&one(pred), &u, &v).map(contrast_recovered),
                shadowed_light: if total > 0.0 { removed / total } else { 0.0 },
            }
        })
        .collect())
}

/// CSV of all rows: `material,light,method,lpips_shadowed,lpips_unshadowed,rmse_log_shadowed,recovered,shadowed_light`
/// (`recovered` empty where the light casts no shadow).
pub fn csv_text(rows: &[ShadowRow]) -> String {
    let mut s = String::from("material,light,method,lpips_shadowed,lpips_unshadowed,rmse_log_shadowed,recovered,shadowed_light\n");
    for r in rows {
        let rec = r.recovered.map(|v| format!("{v:.6}")).unwrap_or_default();
        let _ = writeln!(
            s,
            "{},{},{},{:.6},{:.6},{:.6},{rec},{:.6}",
            r.material, r.light, r.method, r.lpips_shadowed, r.lpips_unshadowed, r.rmse_log_shadowed, r.shadowed_light
        );
    }
    s
}

/// Per-material means of one method: (lpips vs S, lpips vs U, rmse vs S,
/// recovered over the lights that cast a shadow).
fn material_means(rows: &[ShadowRow], method: &str, material: &str) -> (f64, f64, f64, Option<f64>) {
    let mine: Vec<&ShadowRow> = rows.iter().filter(|r| r.method == method && r.material == material).collect();
    let n = mine.len().max(1) as f64;
    let mean = |f: fn(&ShadowRow) -> f64| mine.iter().map(|r| f(r)).sum::<f64>() / n;
    let rec: Vec<f64> = mine.iter().filter_map(|r| r.recovered).collect();
    let rec_mean = (!rec.is_empty()).then(|| rec.iter().sum::<f64>() / rec.len() as f64);
    (mean(|r| r.lpips_shadowed), mean(|r| r.lpips_unshadowed), mean(|r| r.rmse_log_shadowed), rec_mean)
}

/// Markdown summary: means (95% intervals over materials) per method, and
/// per light when there is a single material (the over-fitting figure).
pub fn summary_markdown(opts: &ShadowEvalOptions, rows: &[ShadowRow], methods: &[String], materials: &[String]) -> String {
    let mut s = String::from("# Shadows\n\n");
    let configs = shadow_configs(opts.lights);
    let shadowed: Vec<f64> = rows.iter().filter(|r| r.method == GGX_UNSHADOWED).map(|r| r.shadowed_light).collect();
    let _ = writeln!(
        s,
        "Dataset `{}`, {} material(s) at {}x{}, {} lights per material (elevations {} degrees), height scale {}, {} input photos (shadowed co-located renders). \
         The shadows remove {:.1}% of the un-shadowed light on average.\n",
        opts.dataset,
        materials.len(),
        opts.size,
        opts.size,
        opts.lights,
        SHADOW_ELEVATIONS_DEG.iter().map(|e| format!("{e}")).collect::<Vec<_>>().join("/"),
        opts.shadows.height_scale,
        if opts.ldr_input { "LDR (clamped)" } else { "HDR" },
        100.0 * shadowed.iter().sum::<f64>() / shadowed.len().max(1) as f64,
    );
    let _ = writeln!(s, "| Method | LPIPS vs shadowed reference | LPIPS vs un-shadowed GGX | RMSE ln(1+R) vs shadowed | shadow contrast recovered |");
    let _ = writeln!(s, "|---|---|---|---|---|");
    for method in methods {
        let means: Vec<(f64, f64, f64, Option<f64>)> = materials.iter().map(|m| material_means(rows, method, m)).collect();
        let cell = |v: Vec<f64>| {
            let (m, h) = mean_ci95(&v);
            format!("{m:.3} ± {h:.3}")
        };
        let rec: Vec<f64> = means.iter().filter_map(|x| x.3).collect();
        let _ = writeln!(
            s,
            "| {method} | {} | {} | {} | {} |",
            cell(means.iter().map(|x| x.0).collect()),
            cell(means.iter().map(|x| x.1).collect()),
            cell(means.iter().map(|x| x.2).collect()),
            if rec.is_empty() { "n/a".to_string() } else { cell(rec) }
        );
    }
    if materials.len() == 1 {
        let _ = writeln!(s, "\n## Per light: LPIPS vs shadowed / vs un-shadowed (shadow contrast recovered)\n");
        let _ = writeln!(s, "| Light | elevation | azimuth | shadowed light | {} |", methods.join(" | "));
        let _ = writeln!(s, "|---|---|---|---|{}", "---|".repeat(methods.len()));
        for (k, c) in configs.iter().enumerate() {
            let l = c.light;
            let elevation = (l[2] / (l[0] * l[0] + l[1] * l[1] + l[2] * l[2]).sqrt()).asin().to_degrees();
            let azimuth = l[1].atan2(l[0]).to_degrees();
            let find = |m: &str| rows.iter().find(|r| r.light == k && r.method == m);
            let shadow = find(GGX_UNSHADOWED).map(|r| r.shadowed_light).unwrap_or(0.0);
            let cells: Vec<String> = methods
                .iter()
                .map(|m| match find(m) {
                    Some(r) => format!(
                        "{:.3} / {:.3} ({})",
                        r.lpips_shadowed,
                        r.lpips_unshadowed,
                        r.recovered.map(|v| format!("{v:.2}")).unwrap_or_else(|| "-".into())
                    ),
                    None => "-".into(),
                })
                .collect();
            let _ = writeln!(s, "| {k} | {elevation:.0}° | {azimuth:.0}° | {:.1}% | {} |", 100.0 * shadow, cells.join(" | "));
        }
    }
    s
}

/// Renders of one material: U, V, S and each method's P, all `[K, ., H, W]` on the CPU.
struct MaterialRenders {
    unshadowed: Tensor,
    visibility: Tensor,
    shadowed: Tensor,
    predictions: Vec<Tensor>,
}

fn render_material(m: &Svbrdf, methods: &mut [Box<dyn Method>], opts: &ShadowEvalOptions, configs: &[LightView]) -> Result<(Tensor, MaterialRenders)> {
    let photo_cfg = [LightView::colocated(MODEL_FOV_DEG)];
    let photo = super::reference_renders(m, &photo_cfg) * visibility_maps(m, &photo_cfg, &opts.shadows)?;
    let photo = photo.get(0);
    let photo = if opts.ldr_input { crate::spaces::ldr_clamp(&photo) } else { photo };
    let unshadowed = super::reference_renders(m, configs);
    let visibility = visibility_maps(m, configs, &opts.shadows)?;
    let shadowed = &unshadowed * &visibility;
    let mut predictions = Vec::with_capacity(methods.len());
    for method in methods.iter_mut() {
        method.prepare(&photo)?;
        predictions.push(method.render(configs)?);
    }
    Ok((photo, MaterialRenders { unshadowed, visibility, shadowed, predictions }))
}

/// Grid of one material: a row per light (at most 8): visibility | GGX
/// without shadows | shadowed reference | each method.
fn material_grid(r: &MaterialRenders) -> Result<Image> {
    let k = r.unshadowed.size()[0].min(8);
    let mut rows = Vec::new();
    for i in 0..k {
        let mask = r.visibility.get(i).expand([3, -1, -1], false);
        let mut row = vec![Image::from_tensor(&mask)?, Image::display_of(&r.unshadowed.get(i))?, Image::display_of(&r.shadowed.get(i))?];
        for p in &r.predictions {
            row.push(Image::display_of(&p.get(i))?);
        }
        rows.push(row);
    }
    crate::viz::grid(&rows, 4)
}

/// `flashmat shadow-eval`: scores the methods on shadowed renders and
/// writes `shadows.csv`, `summary.md` and grids of the most shadowed
/// materials (`grid-NAME.jpg`, with the input photo as `photo-NAME.jpg`).
pub fn run(opts: &ShadowEvalOptions) -> Result<Vec<ShadowRow>> {
    ensure!(opts.lights > 0, "--lights must be at least 1");
    super::check_eval_size(opts.size)?;
    opts.shadows.validate()?;
    let mut methods = open_methods(&opts.models, opts.ldr_input, opts.device, &[], &crate::infer::ExposureConfig::default(), None)?;
    let materials = super::load_materials(&opts.dataset, opts.size, opts.limit)?;
    let lpips = Lpips::new(opts.device)?;
    std::fs::create_dir_all(&opts.out).map_err(|e| anyhow!("cannot create output folder {}: {e}", opts.out.display()))?;
    let configs = shadow_configs(opts.lights);

    // The most shadowed materials get grids: rank by the mean shadowed fraction of pixels over the lights.
    let mut shadow_amount: Vec<(f64, usize)> = materials
        .iter()
        .enumerate()
        .map(|(i, (_, m))| {
            let v = visibility_maps(m, &configs, &opts.shadows)?;
            Ok((1.0 - v.mean(Kind::Double).double_value(&[]), i))
        })
        .collect::<Result<_>>()?;
    shadow_amount.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
    let grid_set: Vec<usize> = shadow_amount.iter().take(opts.grids).map(|x| x.1).collect();

    let mut names: Vec<String> = vec![GGX_UNSHADOWED.to_string()];
    names.extend(methods.iter().map(|m| m.name()));
    let bar = if opts.progress { ProgressBar::new(materials.len() as u64) } else { ProgressBar::hidden() };
    bar.set_style(ProgressStyle::with_template("{bar:40} {pos}/{len} materials, {elapsed} (eta {eta}) {msg}").expect("valid template"));
    let mut rows = Vec::new();
    for (i, (name, m)) in materials.iter().enumerate() {
        bar.set_message(name.clone());
        let (photo, r) = render_material(m, &mut methods, opts, &configs).map_err(|e| anyhow!("{name}: {e:#}"))?;
        rows.extend(score_method(&lpips, name, GGX_UNSHADOWED, &r.unshadowed, &r.unshadowed, &r.shadowed, &r.visibility)?);
        for (method, pred) in names[1..].iter().zip(&r.predictions) {
            rows.extend(score_method(&lpips, name, method, pred, &r.unshadowed, &r.shadowed, &r.visibility)?);
        }
        if grid_set.contains(&i) {
            crate::io::write_jpeg(&opts.out.join(format!("grid-{name}.jpg")), &material_grid(&r)?, SHADOW_GRID_JPEG_QUALITY)?;
            crate::io::write_jpeg(&opts.out.join(format!("photo-{name}.jpg")), &Image::display_of(&photo)?, super::report::REPORT_JPEG_QUALITY)?;
        }
        bar.inc(1);
    }
    bar.finish_and_clear();
    let material_names: Vec<String> = materials.iter().map(|(n, _)| n.clone()).collect();
    crate::io::atomic_write_bytes(&opts.out.join("shadows.csv"), csv_text(&rows).as_bytes())?;
    let mut summary = summary_markdown(opts, &rows, &names, &material_names);
    let _ = writeln!(
        summary,
        "\nGrids (`grid-NAME.jpg`, one row per light, at most 8): visibility | GGX without shadows | shadowed GGX reference | {}. Input photos: `photo-NAME.jpg`.",
        names[1..].join(" | ")
    );
    crate::io::atomic_write_bytes(&opts.out.join("summary.md"), summary.as_bytes())?;
    Ok(rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn configs_cycle_elevations_on_the_radius_4_hemisphere_seen_from_the_photo_camera() {
        let c = shadow_configs(8);
        assert_eq!(c.len(), 8);
        assert_eq!(c, shadow_configs(8));
        for (i, lv) in c.iter().enumerate() {
            let l = lv.light;
            let r = (l[0] * l[0] + l[1] * l[1] + l[2] * l[2]).sqrt();
            assert!((r - HEMISPHERE_RADIUS).abs() < 1e-9, "{l:?}");
            let elevation = (l[2] / r).asin().to_degrees();
            assert!((elevation - SHADOW_ELEVATIONS_DEG[i % 4]).abs() < 1e-9, "light {i}: {elevation}");
            let azimuth = l[1].atan2(l[0]).to_degrees().rem_euclid(360.0);
            assert!((azimuth - (15.0 + 45.0 * i as f64)).abs() < 1e-9, "light {i}: {azimuth}");
            assert_eq!(lv.view, LightView::colocated(MODEL_FOV_DEG).view);
        }
    }

    /// U = 1 everywhere; the left half of each image is in shadow.
    fn half_shadow() -> (Tensor, Tensor) {
        let u = Tensor::ones([2, 3, 4, 4], (Kind::Float, Device::Cpu));
        let v = Tensor::cat(&[Tensor::zeros([2, 1, 4, 2], (Kind::Float, Device::Cpu)), Tensor::ones([2, 1, 4, 2], (Kind::Float, Device::Cpu))], 3);
        (u, v)
    }

    #[test]
    fn contrast_is_one_for_the_reference_zero_without_shadows_or_for_a_global_scale() {
        let (u, v) = half_shadow();
        let shadowed = &u * &v;
        assert_eq!(shadow_ratios(&shadowed, &u, &v), Some((0.0, 1.0)));
        assert_eq!(contrast_recovered(shadow_ratios(&shadowed, &u, &v).unwrap()), 1.0);
        assert_eq!(contrast_recovered(shadow_ratios(&u, &u, &v).unwrap()), 0.0);
        // Darkening the whole image is not a shadow.
        let dim = &u * 0.3;
        assert!(contrast_recovered(shadow_ratios(&dim, &u, &v).unwrap()).abs() < 1e-12);
        // Hand value: half as bright in the shadow, 0.8 in the light: 1 - 0.5 / 0.8.
        let half = Tensor::cat(&[Tensor::full([2, 3, 4, 2], 0.5, (Kind::Float, Device::Cpu)), Tensor::full([2, 3, 4, 2], 0.8, (Kind::Float, Device::Cpu))], 3);
        let (dark, lit) = shadow_ratios(&half, &u, &v).unwrap();
        assert!((dark - 0.5).abs() < 1e-7 && (lit - 0.8).abs() < 1e-7, "{dark} {lit}");
        assert!((contrast_recovered((dark, lit)) - 0.375).abs() < 1e-6);
        // No shadow at all: nothing to recover.
        assert_eq!(shadow_ratios(&u, &u, &v.ones_like()), None);
    }

    /// The print-out baseline on one held-out material at 32x32, 4 lights.
    fn small_options(dataset: &str, height_scale: f64, out: &std::path::Path) -> ShadowEvalOptions {
        ShadowEvalOptions {
            models: vec!["printout".into()],
            dataset: dataset.into(),
            out: out.to_path_buf(),
            size: 32,
            limit: None,
            lights: 4,
            shadows: ShadowOptions { height_scale, ..Default::default() },
            ldr_input: false,
            grids: 1,
            device: Device::Cpu,
            progress: false,
        }
    }

    #[test]
    fn flat_materials_cast_no_shadow_and_the_unshadowed_ggx_row_is_exact() {
        let dir = tempfile::tempdir().unwrap();
        let opts = small_options("procedural-test:38", 4.0, dir.path());
        let rows = run(&opts).unwrap();
        assert_eq!(rows.len(), 2 * 4);
        let ggx: Vec<&ShadowRow> = rows.iter().filter(|r| r.method == GGX_UNSHADOWED).collect();
        for r in &ggx {
            assert_eq!(r.lpips_unshadowed, 0.0);
            assert_eq!(r.material, "test38");
        }
        // Test material 38 at height scale 4 is the most shadowed one: its
        // low lights lose light, and the un-shadowed render keeps none of it.
        assert!(ggx[0].shadowed_light > 0.05, "{}", ggx[0].shadowed_light);
        assert!(ggx[0].lpips_shadowed > 0.0);
        assert_eq!(ggx[0].recovered, Some(0.0));
        let csv = std::fs::read_to_string(dir.path().join("shadows.csv")).unwrap();
        assert_eq!(csv.lines().count(), 1 + rows.len());
        let summary = std::fs::read_to_string(dir.path().join("summary.md")).unwrap();
        assert!(summary.contains("| ggx-unshadowed | ") && summary.contains("## Per light"), "{summary}");
        assert!(dir.path().join("grid-test38.jpg").exists() && dir.path().join("photo-test38.jpg").exists());

        // A flat material: no shadows, so every light reports n/a.
        let flat = Svbrdf::uniform(32, 32, [0.5; 3], [0.04; 3], 0.3);
        let configs = shadow_configs(4);
        let v = visibility_maps(&flat, &configs, &ShadowOptions { height_scale: 4.0, ..Default::default() }).unwrap();
        assert_eq!(v.min().double_value(&[]), 1.0);
        let u = super::super::reference_renders(&flat, &configs);
        assert_eq!(shadow_ratios(&u, &u, &v), None);
    }

    #[test]
    fn bad_options_are_refused_with_one_line() {
        let dir = tempfile::tempdir().unwrap();
        let base = small_options("procedural-test:51", 1.0, dir.path());
        let err = |o: ShadowEvalOptions| format!("{:#}", run(&o).unwrap_err());
        assert!(err(base.clone()).contains("0 to 49"));
        assert!(err(ShadowEvalOptions { lights: 0, ..base.clone() }).contains("--lights"));
        let e = err(ShadowEvalOptions { shadows: ShadowOptions { height_scale: f64::NAN, ..Default::default() }, ..base.clone() });
        assert!(e.contains("height scale") && !e.contains('\n'), "{e}");
    }
}
