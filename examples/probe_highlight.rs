//! Where does the near-black highlight spike come from? Estimates the
//! near-black uniform materials of `flashmat eval --uniform`, prints the
//! centre row of the identity render against the truth, the neural map's
//! norm along it, and the identity render with every pixel given one code
//! (the map's mean, and the code of a corner pixel): if the spike survives a
//! constant code it lives in the renderer's direction function, otherwise in
//! M_est's highlight codes (issue 15).
//!
//! ```sh
//! cargo run --release --example probe_highlight -- [MODEL_FILE] [SIZE]
//! ```

use anyhow::Result;
use flashmat::geometry::LightView;
use flashmat::infer::{estimate, load_model, PreparedPhoto};
use tch::Kind;

fn main() {
    // One error line and a non-zero exit for bad input, never a backtrace.
    if let Err(e) = run() {
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}

fn run() -> Result<()> {
    let path = std::env::args().nth(1).map(std::path::PathBuf::from);
    let size: usize = std::env::args().nth(2).map_or(Ok(256), |s| s.parse())?;
    let loaded = load_model(path.as_deref(), tch::Device::Cpu)?;
    let identity = LightView::colocated(flashmat::geometry::MODEL_FOV_DEG);
    let mid = size / 2;
    let cols: Vec<usize> = [0, size / 4, 3 * size / 8, 7 * size / 16, mid - 4, mid - 2, mid - 1, mid, mid + 1].into_iter().collect();
    let row_of = |im: &flashmat::image::Image| -> Vec<f32> { cols.iter().map(|&c| (0..3).map(|ch| im.data[ch * size * size + mid * size + c]).sum::<f32>() / 3.0).collect() };
    let fmt = |v: &[f32]| v.iter().map(|x| format!("{x:8.3}")).collect::<Vec<_>>().join("");
    println!("columns {:?} of row {mid}", cols);
    for (set, u) in flashmat::eval::uniform::uniform_materials() {
        if !["near-black", "white", "blue"].contains(&u.name) { continue; }
        let m = flashmat::svbrdf::Svbrdf::uniform(size, size, u.diffuse, u.specular, u.roughness);
        let truth = flashmat::svbrdf::render::render_material(&m, &[identity])?;
        let photo = PreparedPhoto::at_model_view(truth[0].clone(), loaded.info.ldr_input, "probe");
        let mut mat = estimate(&loaded.model, &loaded.info, &photo)?;
        let pred = mat.render_image(&identity)?;
        let norm = mat.neural_map.square().sum_dim_intlist(&[0i64][..], false, Kind::Float).sqrt();
        let norms: Vec<f32> = cols.iter().map(|&c| norm.double_value(&[mid as i64, c as i64]) as f32).collect();
        println!("\n{set} {}", u.name);
        println!("  truth    {}", fmt(&row_of(&truth[0])));
        println!("  render   {}", fmt(&row_of(&pred)));
        println!("  |code|   {}", fmt(&norms));
        let lum: Vec<f32> = (0..size * size).map(|i| (0..3).map(|c| pred.data[c * size * size + i]).sum::<f32>() / 3.0).collect();
        let (at, peak) = lum.iter().enumerate().fold((0, f32::MIN), |best, (i, &v)| if v > best.1 { (i, v) } else { best });
        let truth_peak = (0..size * size).map(|i| (0..3).map(|c| truth[0].data[c * size * size + i]).sum::<f32>() / 3.0).fold(f32::MIN, f32::max);
        println!("  brightest render pixel {peak:.3} at row {}, column {} (truth's brightest {truth_peak:.3})", at / size, at % size);
        let original = mat.neural_map.copy();
        let mean = original.mean_dim(&[1i64, 2][..], true, Kind::Float);
        mat.neural_map = mean.expand_as(&original).contiguous();
        println!("  mean code{}", fmt(&row_of(&mat.render_image(&identity)?)));
        let corner = original.narrow(1, 4, 1).narrow(2, 4, 1);
        mat.neural_map = corner.expand_as(&original).contiguous();
        println!("  corner   {}", fmt(&row_of(&mat.render_image(&identity)?)));
        let centre = original.narrow(1, mid as i64, 1).narrow(2, mid as i64, 1);
        mat.neural_map = centre.expand_as(&original).contiguous();
        println!("  centre   {}", fmt(&row_of(&mat.render_image(&identity)?)));
    }
    Ok(())
}
