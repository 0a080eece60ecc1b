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
use flashmat::capture::synthetic::{phone_views, shoot, PhoneEffects, SUPERSAMPLE};

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
    let fx = PhoneEffects { jpeg_quality: None, ..Default::default() };
    for (i, (shot, v)) in shoot(&m, &layout, &views, [8.0, 0.0], SUPERSAMPLE, &fx)?.into_iter().zip(&views).enumerate() {
        let path = out.join(format!("IMG_{i:02}.jpg"));
        flashmat::io::write_jpeg(&path, &shot.rgb.to_image(), 90)?;
        let c = v.pose.centre();
        eprintln!("{}: lens at ({:.0}, {:.0}, {:.0}) mm", path.display(), c[0], c[1], c[2]);
    }
    Ok(())
}
