//! Where do the rings and the relit hole of flat dark materials come from?
//! For flat materials (dark brown, dielectric, four roughnesses) photographed
//! with the co-located flash: the estimated neural map's spread (a flat
//! material should get one code), and the renders' radial error against the
//! truth under the input light (identity) and three side lights, for
//! (a) the estimated map and (b) one code for every pixel, fitted with the
//! renderer frozen to all four truths (log-space L1, Adam). If (b) renders
//! the material without rings, the renderer can express it and M_est's
//! position-dependent codes are what rings (issue 15).
//!
//! ```sh
//! cargo run --release --example probe_rings -- [MODEL_FILE] [SIZE]
//! ```

use anyhow::Result;
use flashmat::geometry::{LightView, MODEL_FOV_DEG};
use flashmat::infer::{estimate, load_model, PreparedPhoto};
use flashmat::spaces::to_log;
use flashmat::optim::Adam;
use std::collections::HashMap;
use tch::{Kind, Tensor};

fn main() {
    // One error line and a non-zero exit for bad input, never a backtrace.
    if let Err(e) = run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

/// Mean |error| in log space per ring of radius r (pixels from the centre,
/// 8 rings), and overall. pred, truth: `[K, 3, H, W]` log radiance.
fn ring_errors(pred: &Tensor, truth: &Tensor, size: usize) -> (Vec<f64>, f64) {
    let err = (pred - truth).abs().mean_dim(&[0i64, 1][..], false, Kind::Float); // [H, W]
    let err = Vec::<f32>::try_from(err.flatten(0, -1)).expect("f32 errors");
    let half = size as f64 / 2.0;
    let mut sums = vec![(0.0, 0usize); 8];
    for (i, e) in err.iter().enumerate() {
        let (y, x) = ((i / size) as f64 + 0.5 - half, (i % size) as f64 + 0.5 - half);
        let ring = (((y * y + x * x).sqrt() / half) * 8.0).floor().min(7.0) as usize;
        sums[ring].0 += *e as f64;
        sums[ring].1 += 1;
    }
    let rings = sums.iter().map(|(s, n)| s / (*n).max(1) as f64).collect();
    (rings, err.iter().map(|&e| e as f64).sum::<f64>() / err.len() as f64)
}

fn run() -> Result<()> {
    let path = std::env::args().nth(1).map(std::path::PathBuf::from);
    let size: usize = std::env::args().nth(2).map_or(Ok(128), |s| s.parse())?;
    let loaded = load_model(path.as_deref(), tch::Device::Cpu)?;
    let identity = LightView::colocated(MODEL_FOV_DEG);
    let d = identity.view[2];
    let configs = [
        identity,
        LightView { light: [1.5, 1.0, 2.5], view: identity.view },
        LightView { light: [-1.0, 0.5, 1.5], view: identity.view },
        LightView { light: [0.3, -0.4, d], view: identity.view },
    ];
    println!("log-space |error| per ring (centre -> corner), over identity + 3 side lights");
    for roughness in [0.3f32, 0.45, 0.6, 0.75] {
        let m = flashmat::svbrdf::Svbrdf::uniform(size, size, [0.05, 0.035, 0.025], [0.04; 3], roughness);
        let truths = flashmat::svbrdf::render::render_material(&m, &configs)?;
        let truth = to_log(&Tensor::stack(&truths.iter().map(|im| im.to_tensor()).collect::<Vec<_>>(), 0));
        let photo = PreparedPhoto::at_model_view(truths[0].clone(), loaded.info.ldr_input, "probe");
        let mut mat = estimate(&loaded.model, &loaded.info, &photo)?;
        let (wi, wo) = mat.direction_maps(&configs);
        let map = mat.neural_map.shallow_clone(); // [C, H, W]
        let spread = (&map - map.mean_dim(&[1i64, 2][..], true, Kind::Float)).square().sum_dim_intlist(&[0i64][..], false, Kind::Float).sqrt().mean(Kind::Float).double_value(&[]);
        let norm = map.square().sum_dim_intlist(&[0i64][..], false, Kind::Float).sqrt().mean(Kind::Float).double_value(&[]);
        let est = tch::no_grad(|| mat.renderer.forward_maps(&map.unsqueeze(0), &wi, &wo))?.get(0);
        let (rings, all) = ring_errors(&est, &truth, size);
        println!("\nroughness {roughness}: estimated map mean |code| {norm:.2}, mean distance to its mean code {spread:.2}");
        let fmt = |v: &[f64]| v.iter().map(|x| format!("{x:7.3}")).collect::<Vec<_>>().join("");
        println!("  estimated map   {} | all {all:.4}", fmt(&rings));
        // One code for all pixels, fitted to the four truths.
        let code = map.mean_dim(&[1i64, 2][..], true, Kind::Float).detach().set_requires_grad(true);
        let mut adam = Adam::new(HashMap::from([("code".to_string(), code.shallow_clone())]));
        for _ in 0..150 {
            let pred = mat.renderer.forward_maps(&code.expand_as(&map).unsqueeze(0), &wi, &wo)?.get(0);
            let loss = (&pred - &truth).abs().mean(Kind::Float);
            adam.zero_grad();
            loss.backward();
            adam.step(0.05, None);
        }
        let fitted = tch::no_grad(|| mat.renderer.forward_maps(&code.expand_as(&map).unsqueeze(0), &wi, &wo))?.get(0);
        let (rings, all) = ring_errors(&fitted, &truth, size);
        println!("  one fitted code {} | all {all:.4}", fmt(&rings));
        mat.neural_map = code.detach().expand_as(&map).contiguous();
    }
    Ok(())
}
