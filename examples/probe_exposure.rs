//! How does a model's brightness follow the photo's? For held-out materials,
//! the identity render's mean over the photo's mean when the same 8-bit
//! photo (clamped linear render) is taken at other exposures, with each
//! `--exposure-mode` (off: the photo as it is; normalized; calibrated), and
//! with the photo as it is at several fixed median levels (where the model
//! follows the photo best, issue 53). Prints one line per material: its
//! median level at 0 EV, the ratios per mode and exposure, and per level.
//!
//! ```sh
//! cargo run --release --example probe_exposure -- [MODEL_FILE|-] [COUNT] [SIZE]
//! ```

use anyhow::Result;
use flashmat::geometry::{LightView, MODEL_FOV_DEG};
use flashmat::image::Image;
use flashmat::infer::{estimate_planned, load_model, EstPlan, ExposureConfig, PreparedPhoto};

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

/// Median over pixels of the RGB mean.
fn median_level(im: &Image) -> f32 {
    let n = im.width * im.height;
    let mut lum: Vec<f32> = (0..n).map(|i| (0..3).map(|c| im.data[c * n + i]).sum::<f32>() / 3.0).collect();
    lum.sort_by(f32::total_cmp);
    lum[n / 2]
}

fn run() -> Result<()> {
    let path = std::env::args().nth(1).filter(|p| p != "-").map(std::path::PathBuf::from);
    let count: usize = std::env::args().nth(2).map_or(Ok(50), |s| s.parse())?;
    let size: usize = std::env::args().nth(3).map_or(Ok(256), |s| s.parse())?;
    let loaded = load_model(path.as_deref(), tch::Device::Cpu)?;
    let identity = LightView::colocated(MODEL_FOV_DEG);
    let evs = [-6.0f32, -4.0, 0.0];
    let levels = [0.03f32, 0.1, 0.3];
    let modes = [ExposureConfig::off(), ExposureConfig { calibrate: false, ..Default::default() }, ExposureConfig::default()];
    let ratio = |photo: &Image, mode: &ExposureConfig| -> Result<f32> {
        let p = PreparedPhoto::at_model_view(photo.clone(), true, "probe");
        let m = estimate_planned(&loaded.model, &loaded.info, &p, &EstPlan::Whole, mode, || ())?;
        Ok(m.render_image(&identity)?.mean() / photo.mean())
    };
    println!("material median0 | off, normalized, calibrated: ratio at EV {evs:?} | off: ratio at median {levels:?}");
    for i in 0..count {
        let m = flashmat::data::procedural::test_material(i, size);
        let truth = flashmat::svbrdf::render::render_material(&m, &[identity])?.remove(0);
        let med0 = median_level(&truth.map(|v| v.clamp(0.0, 1.0)));
        let mut line = format!("test{i:02} {med0:7.4} |");
        for mode in &modes {
            for ev in evs {
                let k = 2f32.powf(ev);
                line += &format!(" {:5.2}", ratio(&truth.map(|v| (v * k).clamp(0.0, 1.0)), mode)?);
            }
            line += " |";
        }
        for t in levels {
            let k = t / med0.max(1e-6);
            line += &format!(" {:5.2}", ratio(&truth.map(|v| (v * k).clamp(0.0, 1.0)), &modes[0])?);
        }
        println!("{line}");
    }
    Ok(())
}
