//! Synthetic phone photos of the printed frame (issue 71), to try
//! `flashmat capture` on and to draw the docs' pictures: held-out material
//! I in the 10 cm frame's opening, shot as JPEGs from the overhead spot and
//! around it, with a 26 mm-equivalent lens's focal length, lens
//! distortion, blur, noise and the flash 8 mm beside the lens.
//!
//! ```sh
//! cargo run --release --example frame_photos -- OUT_DIR [PHOTOS=5] [MATERIAL=9] [WIDTH=1600]
//! flashmat capture OUT_DIR/*.jpg --flash-offset 8,0 -o capture/
//! ```

use anyhow::{Context, Result};
use flashmat::capture::frame::FrameLayout;
use flashmat::capture::synthetic::{as_phone_photo, opening_truth, phone_views, render_photo, PhoneEffects, SUPERSAMPLE};

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let out = std::path::PathBuf::from(args.get(1).context("usage: frame_photos OUT_DIR [PHOTOS] [MATERIAL] [WIDTH]")?);
    let count: usize = args.get(2).map_or(Ok(5), |s| s.parse())?;
    let material: usize = args.get(3).map_or(Ok(9), |s| s.parse())?;
    let width: usize = args.get(4).map_or(Ok(1600), |s| s.parse())?;
    let height = width * 3 / 4;
    let focal = 26.0 / flashmat::infer::camera::FULL_FRAME_DIAGONAL_MM * (width as f64).hypot(height as f64);
    let layout = FrameLayout::new(10)?;
    // The overhead photo, then the tilted phones of `TILTED_PHONES` (50 mm a unit): the reflections of their
    // flashes, about straight below them, land in the opening's four quarters.
    let eyes: Vec<[f64; 3]> = std::iter::once([0.0, 0.0, 4.0]).chain(flashmat::data::captures::TILTED_PHONES).take(count).map(|c| c.map(|v| v * 50.0)).collect();
    let views = phone_views(&eyes, &[0.0, 12.0, -20.0, 35.0, 8.0], width, height, focal, -0.03, 0.0);
    let m = flashmat::data::procedural::test_material(material, 256);
    std::fs::create_dir_all(&out)?;
    let flash = |v: &flashmat::capture::synthetic::PhoneView| flashmat::geometry::add(v.pose.centre(), v.pose.to_world_dir([8.0, 0.0, 0.0]));
    let r0 = flashmat::geometry::length(flash(&views[0]));
    for (i, v) in views.iter().enumerate() {
        let light = flash(v);
        let truth = opening_truth(&m, &layout, light, v.pose.centre(), r0)?;
        let linear = render_photo(&layout, &truth, light, r0, v, SUPERSAMPLE)?;
        let rgb = as_phone_photo(&linear, &PhoneEffects { seed: i as u64, jpeg_quality: None, ..Default::default() })?;
        let image = flashmat::image::Image::from_fn(3, height, width, |c, y, x| rgb.data[3 * (y * width + x) + c] as f32 / 255.0);
        let path = out.join(format!("IMG_{i:02}.jpg"));
        flashmat::io::write_jpeg(&path, &image, 90)?;
        let c = v.pose.centre();
        eprintln!("{}: lens at ({:.0}, {:.0}, {:.0}) mm", path.display(), c[0], c[1], c[2]);
    }
    Ok(())
}
