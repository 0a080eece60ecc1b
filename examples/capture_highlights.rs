//! Several photos, one material (issue 70): the moved-highlight test and
//! Identity LPIPS by photo count. For each held-out material, a synthetic
//! capture as a phone takes it (8-bit photos with the flash's 1/r^2
//! fall-off; the flash `FLASH_OFFSET` beside the lens; the positions the
//! fit is told a few millimetres off the true ones), fitted by
//! `estimate --capture`'s path (`fit::photos`: start from the bundled
//! model's estimate of the overhead photo, fitted to GGX), then scored
//! under the moved-highlight lights against the truth:
//!
//! - `single`: the bundled model on the overhead photo (today's default);
//! - `ggx`: the fitted GGX maps rendered directly (the PBR export);
//! - `neural`: the `.nmat` `estimate --capture` writes (the teacher's
//!   encoder and renderer on the fitted maps).
//!
//! LPIPS of the identity (the overhead photo, which the fits saw), of
//! the whole renders under the moved lights (which no photo saw), and of
//! `flashmat eval`'s Reflect and Hemisphere cases (its configurations for
//! seed 0, the first [`CASE_CONFIGS`] of each material's).
//!
//! With FRAME true, nobody tells the positions: each capture is phone
//! photos of the printed frame with the material in its opening
//! (`capture::synthetic`: 1200x900, 26 mm equivalent, lens distortion,
//! blur, noise, JPEG), made into a capture folder by `flashmat capture`'s
//! path (`capture::capture`: tags, camera fit, rectification), then fitted
//! as above (counts of 2 or more).
//!
//! With PHOTOMETRY=1 (environment) as well, the phone locks neither
//! exposure nor white balance and its tone curve is not sRGB: each frame
//! photo at its own exposure (up to +-1 stop) and white balance (up to 10%
//! a channel), through a pure 2.4 gamma; `flashmat capture`'s light meter
//! (`capture::photometry`) is what brings them back to one (LIGHT_METER=0:
//! the folder without its `exposures.txt`, the photos as taken).
//!
//! With BRACKET_STOPS > 0 (told positions only), each position is taken
//! twice, as a phone's exposure bracketing does: at the exposure of the
//! others and that many stops darker (`exposures.txt`). COUNTS are
//! positions; the fit gets twice as many photos.
//!
//! With ORACLE=lobe (environment), the fit starts from the truth's ks and
//! roughness with the estimate's kd and normals; with ORACLE=normals, from
//! the truth's normals and the estimate's other maps; with ORACLE=maps,
//! from all the truth's maps: how far the fit gets when its start is right.
//! PHONES=0,2 (environment) takes the tilted photos from those entries
//! of `TILTED_PHONES`, in that order (default 0,1,2,3: the issue's
//! positions first).
//!
//! BASELINE_TEACHER=FILE adds `neural-before`: the neural material of that
//! teacher's codes as they are (the capture path before issue 83).
//! TEACHER=FILE makes the neural material with that teacher, CODE_STEPS=N
//! fits its codes N steps (0: the teacher's codes as they are), SET=metals
//! scores the coloured-metal set (`data::procedural::metal_material`,
//! MATERIALS its indices) instead of the 50.
//!
//! DNG_BITS=12 (environment; told positions, clean photos) writes each
//! capture as linear DNGs of that many bits in place of the 8-bit PNGs
//! (`PhotoFiles::Dng`: the brightest value of the photos at 0.95 of the
//! white level, nothing clipped, BaselineExposure bringing them back): the
//! RAW twin of the PNG capture. DNG_HEADROOM=4 as well: as a phone exposes
//! for the diffuse, the normal exposure's white at most 4 stops under the
//! sensor's, the peaks above clipped. With NOISE_AND_JPEG true, the DNGs
//! get the JPEG twin's noise in linear terms (no JPEG). Needs `--features raw`.
//!
//! LOBES=1 prints the median roughness and ks of the truth and the fit on
//! the photographed and the moved highlights, the fit's mean normal error,
//! the ghost per moved light on the photographed highlight's clipped
//! and unclipped pixels apart, and the ghost of the fitted maps with the
//! truth's kd, lobe or normals swapped in (which maps carry it).
//!
//! ```sh
//! cargo run --release --example capture_highlights -- [SIZE] [MATERIALS] [COUNTS] [STEPS] [PULL] [SMOOTH] [REGIONS] [LOBE_WEIGHT] [PICTURES_DIR or -] [COARSE_SHARE] [PHOTO_GAINS] [NOISE_AND_JPEG] [FRAME] [BRACKET_STOPS] [LOBE_SHIFT_REGIONS] [CLIPPED_TAIL_WEIGHT] [REGIONAL_START_LOBE] [CLIPPED_NORMAL_SMOOTH_WEIGHT]
//! # defaults: 128 0-5 1,2,3,5 and PhotoFitConfig's steps, pull and smoothness weights; "-" keeps a default
//! ```

use anyhow::Result;
use flashmat::data::captures::{write_synthetic_as, write_synthetic_exposed, Captures, PhotoFiles, TILTED_PHONES};
use flashmat::eval::highlights::{self, HighlightConfig, MaterialHighlights};
use flashmat::fit::photos::{estimated_start, fit_capture, fit_photos, load_capture, load_teacher, fitted_neural_material, start_fit_config, PhotoFitConfig};
use flashmat::geometry::{LightView, Sampling, MODEL_FOV_DEG};
use flashmat::lpips::Lpips;
use rand::{Rng, SeedableRng};
use std::collections::BTreeMap;
use tch::{Device, Tensor};

/// The flash beside the lens (flashmat units: 0.15 is about 1 cm on a
/// 13 cm sample), along +x.
const FLASH_OFFSET: f64 = 0.15;

/// Standard deviation of the position error the fit is told (per axis,
/// flashmat units: 0.03 is about 2 mm).
const POSITION_ERROR: f64 = 0.03;

/// Configurations per material of the Reflect and Hemisphere cases (the
/// paper's 128 take 4x the time).
const CASE_CONFIGS: usize = 32;

/// One method's scores on one material.
struct Scored {
    highlights: MaterialHighlights,
    identity: f64,
    moved: f64,
    lobe_8bit: Option<f64>,
    reflect: f64,
    hemisphere: f64,
}

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let size: usize = args.get(1).filter(|a| *a != "-").map_or(Ok(128), |s| s.parse())?;
    let (first, last): (usize, usize) = match args.get(2) {
        Some(r) => {
            let (a, b) = r.split_once('-').unwrap_or((r, r));
            (a.parse()?, b.parse()?)
        }
        None => (0, 5),
    };
    let counts: Vec<usize> = args.get(3).filter(|a| *a != "-").map_or(Ok(vec![1, 2, 3, 5]), |s| s.split(',').map(|c| c.parse()).collect())?;
    let defaults = PhotoFitConfig::default();
    let steps: usize = args.get(4).filter(|a| *a != "-").map_or(Ok(defaults.steps), |s| s.parse())?;
    let pull_weight: f64 = args.get(5).filter(|a| *a != "-").map_or(Ok(defaults.pull_weight), |s| s.parse())?;
    let smooth_weight: f64 = args.get(6).filter(|a| *a != "-").map_or(Ok(defaults.smooth_weight), |s| s.parse())?;
    let lobe_regions: usize = args.get(7).filter(|a| *a != "-").map_or(Ok(defaults.lobe_regions), |s| s.parse())?;
    let lobe_weight: f64 = args.get(8).filter(|a| *a != "-").map_or(Ok(defaults.lobe_weight), |s| s.parse())?;
    // Pictures per material: the photos of the largest capture and the relit grid.
    let pictures: Option<std::path::PathBuf> = args.get(9).filter(|a| *a != "-").map(Into::into);
    let coarse_share: f64 = args.get(10).filter(|a| *a != "-").map_or(Ok(defaults.coarse_share), |s| s.parse())?;
    let photo_gains: bool = args.get(11).filter(|a| *a != "-").map_or(Ok(defaults.photo_gains), |s| s.parse())?;
    // Phone photos: sensor noise, then JPEG at quality 90, instead of clean PNGs.
    let phone_jpeg: bool = args.get(12).filter(|a| *a != "-").map_or(Ok(false), |s| s.parse())?;
    let frame: bool = args.get(13).filter(|a| *a != "-").map_or(Ok(false), |s| s.parse())?;
    let photometry = std::env::var("PHOTOMETRY").is_ok_and(|v| v == "1");
    anyhow::ensure!(frame || !photometry, "PHOTOMETRY=1 needs FRAME true");
    let bracket_stops: f64 = args.get(14).filter(|a| *a != "-").map_or(Ok(0.0), |s| s.parse())?;
    let lobe_shift_regions: usize = args.get(15).filter(|a| *a != "-").map_or(Ok(defaults.lobe_shift_regions), |s| s.parse())?;
    let clipped_tail_weight: f64 = args.get(16).filter(|a| *a != "-").map_or(Ok(defaults.clipped_tail_weight), |s| s.parse())?;
    let regional_start_lobe: bool = args.get(17).filter(|a| *a != "-").map_or(Ok(defaults.regional_start_lobe), |s| s.parse())?;
    let clipped_normal_smooth_weight: f64 = args.get(18).filter(|a| *a != "-").map_or(Ok(defaults.clipped_normal_smooth_weight), |s| s.parse())?;
    // Diagnostics from the environment: ORACLE=lobe, normals or maps fits from the truth's
    // lobes or normals (the rest estimated) or from all its maps; LOBES=1 prints the lobes' medians.
    let oracle = std::env::var("ORACLE").ok();
    anyhow::ensure!(oracle.as_deref().is_none_or(|o| ["lobe", "normals", "maps"].contains(&o)), "ORACLE must be lobe, normals or maps");
    let print_lobes = std::env::var_os("LOBES").is_some();
    // PHONES=0,2: which of TILTED_PHONES the tilted photos take, in order (default all, in theirs).
    let phones: Vec<usize> = match std::env::var("PHONES") {
        Ok(list) => list.split(',').map(|j| j.trim().parse::<usize>().ok().filter(|&j| j < TILTED_PHONES.len())).collect::<Option<_>>().ok_or_else(|| anyhow::anyhow!("PHONES must list indices below {}, got {list:?}", TILTED_PHONES.len()))?,
        Err(_) => (0..TILTED_PHONES.len()).collect(),
    };
    anyhow::ensure!(bracket_stops >= 0.0 && !(frame && bracket_stops > 0.0), "BRACKET_STOPS must be >= 0, and 0 with FRAME");
    let loaded = flashmat::infer::load_model(None, Device::Cpu)?;
    // TEACHER=FILE: the teacher of the neural material (default the bundled one);
    // CODE_STEPS=N: its code fit's steps (0: the teacher's codes as they are).
    let teacher = load_teacher(std::env::var_os("TEACHER").map(std::path::PathBuf::from).as_deref(), Device::Cpu)?;
    let code_steps: Option<usize> = std::env::var("CODE_STEPS").ok().map(|s| s.parse()).transpose()?;
    // BASELINE_TEACHER=FILE: also the neural material of that teacher's codes as they are (`neural-before`).
    let baseline_teacher = std::env::var_os("BASELINE_TEACHER").map(|f| load_teacher(Some(std::path::Path::new(&f)), Device::Cpu)).transpose()?;
    // SET=metals: the coloured-metal set (data::procedural::metal_material) in place of the 50.
    let metals = std::env::var("SET").is_ok_and(|s| s == "metals");
    // DNG_BITS=12: the told-position captures as linear DNGs of that many bits;
    // DNG_HEADROOM=4: their normal white at most 4 stops under the sensor's.
    let dng_bits: Option<u32> = std::env::var("DNG_BITS").ok().map(|b| b.parse()).transpose()?;
    let max_headroom_stops: f64 = std::env::var("DNG_HEADROOM").ok().map(|b| b.parse()).transpose()?.unwrap_or(f64::INFINITY);
    anyhow::ensure!(dng_bits.is_none() || !frame, "DNG_BITS needs told positions");
    let lpips = Lpips::new(Device::Cpu)?;
    let moved = HighlightConfig::default();
    let overhead = LightView::colocated(MODEL_FOV_DEG);
    let mut rows: BTreeMap<(usize, &str), Vec<Scored>> = BTreeMap::new();
    let t0 = std::time::Instant::now();
    for i in first..=last {
        let m = if metals { flashmat::data::procedural::metal_material(i, size) } else { flashmat::data::procedural::test_material(i, size) };
        let truth = flashmat::eval::reference_renders(&m, &moved.configs()); // [L, 3, H, W]
        let truth_identity = flashmat::eval::colocated_render(&m);
        let s_in = highlights::highlight_mask(&highlights::luminance(&truth_identity)?, moved.threshold);
        let gloss = highlights::glossiness(&m);
        let name = if metals { flashmat::data::procedural::METAL_MATERIALS[i].to_string() } else { format!("test{i:02}") };
        let cases: Vec<(Vec<LightView>, Tensor)> = [Sampling::Reflect, Sampling::Hemisphere]
            .into_iter()
            .map(|c| {
                let cfg = flashmat::eval::case_configs(c, 0, i, CASE_CONFIGS);
                let truth = flashmat::eval::reference_renders(&m, &cfg);
                (cfg, truth)
            })
            .collect();
        // A method's renders under its configurations `[K, 3, H, W]`.
        let score = |render: &dyn Fn(&[LightView]) -> Result<Tensor>| -> Result<Scored> {
            let pred = render(&moved.configs())?;
            let identity = render(&[overhead])?.get(0);
            let (pred, identity) = (&pred, &identity);
            let row = highlights::material_highlights(&name, gloss, 0, &highlights::light_ratios(&s_in, pred, &truth, &moved, None)?);
            // The lobe as an 8-bit photo under the moved lights would show it (both renders clipped at 1).
            let clipped = highlights::light_ratios(&s_in, &pred.clamp_max(1.0), &truth.clamp_max(1.0), &moved, None)?;
            let lobe_8bit = highlights::material_highlights(&name, gloss, 0, &clipped).lobe;
            let lp = flashmat::eval::score_renders(&lpips, &identity.unsqueeze(0), &truth_identity.unsqueeze(0))?[0].lpips;
            let mean_lpips = |pred: &Tensor, truth: &Tensor| -> Result<f64> { Ok(flashmat::eval::score_renders(&lpips, pred, truth)?.iter().map(|s| s.lpips).sum::<f64>() / truth.size()[0] as f64) };
            let moved_lp = mean_lpips(pred, &truth)?;
            let [reflect, hemisphere] = [0, 1].map(|c| mean_lpips(&render(&cases[c].0)?, &cases[c].1));
            let (reflect, hemisphere) = (reflect?, hemisphere?);
            let f = |v: Option<f64>| v.map_or("-".into(), |v| format!("{v:.2}"));
            eprintln!(
                "  {name} (glossiness {gloss:.2}): ghost {} lobe {} (8-bit {}) rest {} LPIPS identity {lp:.3} moved {moved_lp:.3} reflect {reflect:.3} hemisphere {hemisphere:.3}",
                f(row.ghost),
                f(row.lobe),
                f(lobe_8bit),
                f(row.rest)
            );
            Ok(Scored { highlights: row, identity: lp, moved: moved_lp, lobe_8bit, reflect, hemisphere })
        };
        let mut rng = rand_pcg::Pcg64::seed_from_u64(70 + i as u64);
        // Relit grid columns (label, renders under the moved lights [L, 3, H, W]), truth first.
        let mut relit: Vec<(String, Tensor)> = vec![("truth".into(), truth.shallow_clone())];
        for &k in &counts {
            // Overhead, then the tilted phones of `TILTED_PHONES` (in PHONES' order when given).
            let tilted: Vec<[f64; 3]> = phones.iter().map(|&j| TILTED_PHONES[j]).collect();
            let cameras: Vec<[f64; 3]> = std::iter::once(overhead.view).chain(tilted).take(k).collect();
            let positions: Vec<LightView> = cameras.iter().map(|&c| LightView { light: [c[0] + FLASH_OFFSET, c[1], c[2]], view: c }).collect();
            // Photo j of a bracketed capture is position j / 2 at exposure 1 (even j) or darker (odd j).
            let shots = if bracket_stops > 0.0 { 2 } else { 1 };
            let truths: Vec<LightView> = positions.iter().flat_map(|&c| std::iter::repeat_n(c, shots)).collect();
            let exposures: Vec<f64> = (0..truths.len()).map(|j| if j % 2 == 1 && shots == 2 { 0.5f64.powf(bracket_stops) } else { 1.0 }).collect();
            let photos_taken = truths.len();
            let dir = tempfile::tempdir()?;
            if frame {
                anyhow::ensure!(k >= 2, "a capture of the printed frame needs 2 or more photos");
                frame_capture(&m, &cameras, dir.path(), i, photometry)?;
            } else {
                match dng_bits {
                    Some(bits) => write_synthetic_as(dir.path(), &m, &truths, &exposures, 2.0, PhotoFiles::Dng { bits, max_headroom_stops })?,
                    None => write_synthetic_exposed(dir.path(), &m, &truths, &exposures, 2.0)?,
                }
                // Noise of 1% of the display value plus 0.4% (about one 8-bit step), as a phone's processed photo.
                let display_sigma = |d: f32| 0.01 * d + 0.004;
                // Photo j's standard normals: their own generator, so the told positions match the clean run's.
                let normals = |j: usize, n: usize| -> Vec<f32> {
                    let mut noise_rng = rand_pcg::Pcg64::seed_from_u64(7000 + 10 * i as u64 + j as u64);
                    (0..n).map(|_| rand_distr::Distribution::<f32>::sample(&rand_distr::StandardNormal, &mut noise_rng)).collect()
                };
                if let (true, Some(bits)) = (phone_jpeg, dng_bits) {
                    for j in 0..photos_taken {
                        // The JPEG twin's noise in the same photons: its display-space sigma taken to linear (dv = 2.2 d^1.2 dd).
                        let path = dir.path().join(format!("{j:02}.dng"));
                        let (photo, gain) = (flashmat::io::read_image(&path)?, flashmat::io::raw_baseline_gain(&path));
                        let (h, w) = (photo.height, photo.width);
                        let z = normals(j, 3 * h * w);
                        let noisy = flashmat::image::Image::from_fn(3, h, w, |c, y, x| {
                            let v = photo.get(c, y, x) * gain as f32;
                            let d = v.max(0.0).powf(1.0 / 2.2);
                            let sigma = 2.2 * d.powf(1.2) * display_sigma(d);
                            ((v + sigma * z[(c * h + y) * w + x]) / gain as f32).clamp(0.0, 1.0)
                        });
                        let opts = flashmat::io::dng::DngOptions { bits, baseline_exposure: gain.log2(), ..Default::default() };
                        flashmat::io::dng::write_dng(&path, &noisy, &opts)?;
                    }
                } else if phone_jpeg {
                    for j in 0..photos_taken {
                        let png = dir.path().join(format!("{j:02}.png"));
                        let photo = flashmat::io::read_image(&png)?;
                        let (h, w) = (photo.height, photo.width);
                        let z = normals(j, 3 * h * w);
                        let noisy = flashmat::image::Image::from_fn(3, h, w, |c, y, x| {
                            let v = photo.get(c, y, x);
                            (v + display_sigma(v) * z[(c * h + y) * w + x]).clamp(0.0, 1.0)
                        });
                        flashmat::io::write_jpeg(&dir.path().join(format!("{j:02}.jpg")), &noisy, 90)?;
                        std::fs::remove_file(&png)?;
                    }
                }
                // What the phone's pose estimate would say: a few millimetres off.
                let mut told = |p: [f64; 3]| p.map(|v| v + POSITION_ERROR * (rng.random::<f64>() * 2.0 - 1.0) * 3f64.sqrt());
                // A bracket's photos share their position (one burst).
                let lines = |pick: fn(&LightView) -> [f64; 3], told: &mut dyn FnMut([f64; 3]) -> [f64; 3]| -> String {
                    positions.iter().map(|c| told(pick(c))).map(|p| format!("{:.6},{:.6},{:.6}\n", p[0], p[1], p[2]).repeat(shots)).collect()
                };
                let cams = lines(|c| c.view, &mut told);
                let lights = lines(|c| c.light, &mut told);
                std::fs::write(dir.path().join("camera_pos.txt"), cams)?;
                std::fs::write(dir.path().join("light_pos.txt"), lights)?;
            }
            let capture = load_capture(&Captures::open(dir.path())?, k * shots, size)?;
            let photo = capture.photos.get(capture.overhead as i64);
            if k == counts[0] {
                let single = flashmat::infer::estimate(
                    &loaded.model,
                    &loaded.info,
                    &flashmat::infer::PreparedPhoto::at_model_view(flashmat::image::Image::from_tensor(&photo.clamp(0.0, 1.0))?, true, "overhead"),
                )?;
                rows.entry((0, "single")).or_default().push(score(&|c| single.render(c))?);
                relit.push(("bundled model, 1 photo".into(), single.render(&moved.configs())?));
            }
            let mut cfg = PhotoFitConfig { steps, size, pull_weight, smooth_weight, lobe_regions, lobe_weight, lobe_shift_regions, clipped_tail_weight, clipped_normal_smooth_weight, regional_start_lobe, coarse_share, photo_gains, ..PhotoFitConfig::default() };
            if let Some(n) = code_steps {
                cfg.code_fit.steps = n;
            }
            let fit = match oracle.as_deref() {
                None => fit_capture(&loaded, &capture, &cfg, Device::Cpu, |_, _, _| {})?,
                Some(o) => {
                    // The fit from a start that holds the truth's lobes (ks, roughness) or all its maps.
                    let truth_maps = m.stacked().to_tensor();
                    let estimate = || estimated_start(&loaded, &photo, &start_fit_config(), |_, _| {});
                    let start = match o {
                        "lobe" => {
                            let start = estimate()?;
                            Tensor::cat(&[start.narrow(0, 0, 3), truth_maps.narrow(0, 3, 4), start.narrow(0, 7, 3)], 0)
                        }
                        "normals" => Tensor::cat(&[estimate()?.narrow(0, 0, 7), truth_maps.narrow(0, 7, 3)], 0),
                        _ => truth_maps,
                    };
                    fit_photos(&capture.photos, &capture.clipped, &capture.configs, &start, &cfg, |_| {})?
                }
            };
            // GGX maps `[10, H, W]` rendered under configurations: `[K, 3, H, W]`.
            let render_maps = |maps: &Tensor, configs: &[LightView]| -> Tensor {
                let (l, v) = flashmat::geometry::config_tensors(configs, Device::Cpu);
                let n = configs.len() as i64;
                flashmat::svbrdf::render::render(&maps.unsqueeze(0), &l.view([1, n, 3]), &v.view([1, n, 3])).get(0)
            };
            let render = |configs: &[LightView]| -> Result<Tensor> { Ok(render_maps(&fit.maps, configs)) };
            if print_lobes {
                // Medians of the truth's and the fit's roughness and ks (RGB mean) on the overhead
                // photo's highlight and on the moved lights' highlights outside it.
                let mut moved_mask = vec![false; s_in.len()];
                for l in 0..truth.size()[0] {
                    let mask = highlights::highlight_mask(&highlights::luminance(&truth.get(l))?, moved.threshold);
                    moved_mask.iter_mut().zip(mask.iter().zip(&s_in)).for_each(|(o, (&lit, &seen))| *o |= lit && !seen);
                }
                let flat = |t: Tensor| -> Result<Vec<f32>> { Ok(Vec::try_from(t.reshape([-1]))?) };
                let rgb_mean = |t: Tensor| t.mean_dim(0, false, tch::Kind::Float);
                let (tr, tk) = (flat(m.roughness.to_tensor())?, flat(rgb_mean(m.specular.to_tensor()))?);
                let (fr, fk) = (flat(fit.maps.get(6))?, flat(rgb_mean(fit.maps.narrow(0, 3, 3)))?);
                let median = |v: &[f32], mask: &[bool]| {
                    let mut x: Vec<f32> = v.iter().zip(mask).filter(|(_, &inside)| inside).map(|(&a, _)| a).collect();
                    x.sort_by(|a, b| a.total_cmp(b));
                    x.get(x.len() / 2).copied().unwrap_or(f32::NAN)
                };
                let pair = |t: &[f32], f: &[f32], mask: &[bool]| format!("{:.3}/{:.3}", median(t, mask), median(f, mask));
                // Mean angle between the fit's normals and the truth's, in degrees.
                let cos = (fit.maps.narrow(0, 7, 3) * m.normal.to_tensor()).sum_dim_intlist([0i64].as_slice(), false, tch::Kind::Float).clamp(-1.0, 1.0);
                let normal_error = cos.acos().mean(tch::Kind::Double).double_value(&[]).to_degrees();
                let clipped_overhead: Vec<bool> = Vec::<bool>::try_from(capture.clipped.get(capture.overhead as i64).reshape([-1]))?;
                // Issue 84: the normals where the overhead photo clipped against elsewhere (median degrees).
                let angles: Vec<f32> = flat(cos.acos() * (180.0 / std::f64::consts::PI))?;
                let unclipped: Vec<bool> = clipped_overhead.iter().map(|c| !c).collect();
                eprintln!(
                    "  normals of {name} where the overhead photo clipped ({} px): median {:.2} degrees off; elsewhere {:.2}",
                    clipped_overhead.iter().filter(|&&b| b).count(),
                    median(&angles, &clipped_overhead),
                    median(&angles, &unclipped)
                );
                let pred = render(&moved.configs())?;
                for (label, keep) in [("clipped", true), ("unclipped", false)] {
                    let mask: Vec<bool> = s_in.iter().zip(&clipped_overhead).map(|(&a, &c)| a && c == keep).collect();
                    let ratios = highlights::light_ratios(&mask, &pred, &truth, &moved, None)?;
                    let g: Vec<String> = ratios.iter().map(|r| r.ghost.map_or("-".into(), |v| format!("{v:.2}"))).collect();
                    eprintln!("  ghost of {name} on the {label} photographed highlight ({} px): {}", mask.iter().filter(|&&b| b).count(), g.join(" "));
                }
                // The ghost with one group of the fit's channels replaced by the truth's: which maps carry it.
                let truth_maps = m.stacked().to_tensor();
                let swaps: Vec<String> = [("kd", 0, 3), ("lobe", 3, 4), ("normals", 7, 3)]
                    .iter()
                    .map(|&(label, first, count)| -> Result<String> {
                        let mixed = fit.maps.copy();
                        mixed.narrow(0, first, count).copy_(&truth_maps.narrow(0, first, count));
                        let pred = render_maps(&mixed, &moved.configs());
                        let row = highlights::material_highlights(&name, gloss, 0, &highlights::light_ratios(&s_in, &pred, &truth, &moved, None)?);
                        Ok(format!("{label} {}", row.ghost.map_or("-".into(), |g| format!("{g:.2}"))))
                    })
                    .collect::<Result<_>>()?;
                eprintln!("  ghost of {name} with the truth's maps swapped in: {}", swaps.join(", "));
                eprintln!(
                    "  lobes of {name}, {k} photo(s), truth/fit: photographed highlight r {} ks {}; moved highlights r {} ks {}; normals {normal_error:.2} degrees off",
                    pair(&tr, &fr, &s_in),
                    pair(&tk, &fk, &s_in),
                    pair(&tr, &fr, &moved_mask),
                    pair(&tk, &fk, &moved_mask)
                );
            }
            rows.entry((k, "ggx")).or_default().push(score(&render)?);
            relit.push((format!("GGX maps, {k} photo(s)"), render(&moved.configs())?));
            if let Some(before) = &baseline_teacher {
                let material = flashmat::fit::photos::neural_material(&fit.maps, &photo, before, "capture")?;
                rows.entry((k, "neural-before")).or_default().push(score(&|c| material.render(c))?);
                relit.push((format!("fit, {k} photo(s), neural before"), material.render(&moved.configs())?));
            }
            let (material, code_fit) = fitted_neural_material(&fit.maps, &photo, &teacher, &capture.configs, &cfg.code_fit, "capture")?;
            rows.entry((k, "neural")).or_default().push(score(&|c| material.render(c))?);
            let gap = flashmat::fit::codes::neural_gap(&material, &fit.maps, &flashmat::fit::codes::held_out_configs(4), None)?;
            eprintln!(
                "  gap of {name}'s neural material to its maps: log L1 {:.4}, channel |ln ratio| {:.3}, chromaticity {:.4} (pixels) {:.4} (mean colour); code fit {:.1} s, kept {}",
                gap.log_l1, gap.channel_log_ratio, gap.chromaticity, gap.mean_chromaticity, code_fit.seconds, code_fit.kept
            );
            relit.push((format!("fit, {k} photo(s)"), material.render(&moved.configs())?));
            if let (Some(out), true) = (&pictures, k == *counts.iter().max().unwrap_or(&k)) {
                let cells: Vec<flashmat::image::Image> = (0..k).map(|j| flashmat::image::Image::display_of(&capture.photos.get(j as i64))).collect::<Result<_>>()?;
                std::fs::create_dir_all(out)?;
                flashmat::io::write_jpeg(&out.join(format!("photos-{name}.jpg")), &flashmat::viz::grid(&[cells], 4)?, 80)?;
            }
            eprintln!("{name}, {k} photo(s): data term {:.4} -> {:.4} in {:.1} s, gains {:?}", fit.report.data_before, fit.report.data_after, fit.report.seconds, fit.report.photo_gains.iter().map(|g| format!("{g:.3}")).collect::<Vec<_>>());
        }
        if let Some(out) = &pictures {
            // Rows: the moved lights; columns: truth, the bundled model, per photo count the GGX maps and the neural materials.
            let grid: Vec<Vec<flashmat::image::Image>> = (0..truth.size()[0])
                .map(|l| relit.iter().map(|(_, r)| flashmat::image::Image::display_of(&r.get(l))).collect::<Result<_>>())
                .collect::<Result<_>>()?;
            flashmat::io::write_jpeg(&out.join(format!("relit-{name}.jpg")), &flashmat::viz::grid(&grid, 4)?, 80)?;
            eprintln!("{}: columns {}", out.join(format!("relit-{name}.jpg")).display(), relit.iter().map(|(l, _)| l.as_str()).collect::<Vec<_>>().join(" | "));
        }
    }
    println!("| photos | method | ghost | lobe | lobe, 8-bit | rest | LPIPS identity | LPIPS moved lights | LPIPS Reflect | LPIPS Hemisphere |\n|---|---|---|---|---|---|---|---|---|---|");
    for ((k, method), v) in &rows {
        let s = highlights::summarize(&v.iter().map(|r| &r.highlights).collect::<Vec<_>>());
        let mean = |f: fn(&Scored) -> f64| v.iter().map(f).sum::<f64>() / v.len() as f64;
        let lobes_8bit: Vec<f64> = v.iter().filter_map(|r| r.lobe_8bit).collect();
        let lobe_8bit = flashmat::eval::metrics::geometric_mean(&lobes_8bit);
        let cell = |r: &highlights::RatioStats| format!("{:.2} ({}/{})", r.geo_mean, r.n, v.len());
        let k = if *k == 0 { "1 (model)".to_string() } else { k.to_string() };
        println!(
            "| {k} | {method} | {} | {} | {lobe_8bit:.2} | {} | {:.3} | {:.3} | {:.3} | {:.3} |",
            cell(&s.ghost),
            cell(&s.lobe),
            cell(&s.rest),
            mean(|r| r.identity),
            mean(|r| r.moved),
            mean(|r| r.reflect),
            mean(|r| r.hemisphere)
        );
    }
    println!("\n{} materials at {size}x{size}, {steps} fit steps, pull {pull_weight}, smoothness {smooth_weight}, {lobe_regions} lobe regions at weight {lobe_weight}, coarse share {coarse_share}, photo gains {photo_gains}, noise and JPEG {phone_jpeg}, bracket {bracket_stops} stops, lobe shift regions {lobe_shift_regions}, clipped tail weight {clipped_tail_weight}, clipped normals' smoothness {clipped_normal_smooth_weight}, regional start lobe {regional_start_lobe}, {:.0} s", last + 1 - first, t0.elapsed().as_secs_f64());
    Ok(())
}

/// A capture folder in `dir` made as `flashmat capture` makes it: phone
/// photos of the 10 cm frame from `cameras` (flashmat units, the opening
/// spanning [-1, 1]: 50 mm a unit), the flash `FLASH_OFFSET` beside each
/// lens along the camera's x, the material in the opening (its texels
/// about 2.8 photo pixels across).
fn frame_capture(m: &flashmat::svbrdf::Svbrdf, cameras: &[[f64; 3]], dir: &std::path::Path, seed: usize, photometry: bool) -> Result<()> {
    let size = m.width();
    use flashmat::capture::{frame::FrameLayout, synthetic, CaptureConfig, FramePhoto};
    let layout = FrameLayout::new(10)?;
    let unit = layout.opening_mm() / 2.0;
    let eyes: Vec<[f64; 3]> = cameras.iter().map(|c| c.map(|v| v * unit)).collect();
    let views = synthetic::phone_views(&eyes, &[0.0, 12.0, -20.0, 35.0, 8.0], 1200, 900, 901.3, -0.03, 0.0);
    let offset = [FLASH_OFFSET * unit, 0.0];
    let fx = synthetic::PhoneEffects { seed: 100 * seed as u64, ..Default::default() };
    let photos: Vec<FramePhoto> = synthetic::shoot(m, &layout, &views, offset, synthetic::SUPERSAMPLE, &fx)?
        .into_iter()
        .enumerate()
        .map(|(j, mut s)| {
            if photometry {
                // As a phone without exposure and white-balance lock: photo j
                // at STOPS[j] and WHITE[j] (the overhead photo as shot), all
                // through a pure 2.4 gamma where the reader assumes sRGB.
                const STOPS: [f32; 5] = [0.0, -1.0, 0.6, 1.0, -0.5];
                const WHITE: [[f32; 3]; 5] = [[1.0; 3], [1.1, 1.0, 0.9], [0.92, 1.0, 1.08], [1.05, 1.0, 0.95], [0.9, 1.0, 1.1]];
                let gain: [f32; 3] = std::array::from_fn(|c| 2f32.powf(STOPS[j % 5]) * WHITE[j % 5][c]);
                s.rgb.data.iter_mut().enumerate().for_each(|(i, code)| {
                    let linear = flashmat::spaces::photo_decode(*code as f32 / 255.0) * gain[i % 3];
                    *code = flashmat::spaces::quantize_u8(linear.clamp(0.0, 1.0).powf(1.0 / 2.4));
                });
            }
            FramePhoto { path: format!("IMG_{j}.jpg").into(), rgb: s.rgb, exif_focal: Some(901.3), orientation: 1, exposure: None, raw: None }
        })
        .collect();
    // Rectified at twice the material's side, so the fit's 2x2 shrink lines up with its texels.
    let cfg = CaptureConfig { flash_offset_mm: offset, max_side: 2 * size, ..Default::default() };
    let capture = flashmat::capture::capture(&photos, &cfg, |_, _, _| {})?;
    for (p, v) in capture.photos.iter().zip(&views) {
        let off = flashmat::geometry::length(flashmat::geometry::sub(p.camera, v.pose.centre()));
        eprintln!("    {}: lens {off:.2} mm off, reprojection {:.2} px", p.source.display(), p.rms);
    }
    let folder = dir.join("capture");
    flashmat::capture::write_folder(&capture, &folder, &photos)?;
    if std::env::var("LIGHT_METER").is_ok_and(|v| v == "0") {
        // What the fit gets without the light meter: the photos as taken.
        let _ = std::fs::remove_file(folder.join(flashmat::data::captures::EXPOSURES_FILE));
    }
    for entry in std::fs::read_dir(&folder)? {
        let entry = entry?;
        std::fs::rename(entry.path(), dir.join(entry.file_name()))?;
    }
    Ok(())
}
