//! Estimate a neural material from a flash photo and relight it, through the
//! library API (what `flashmat relight` does, in a page):
//!
//! ```sh
//! cargo run --release --example relight_photo -- [PHOTO] [OUT_DIR]
//! # defaults: examples/photos/IMG_6950.png, out/relight_photo
//! ```

use anyhow::Result;
use flashmat::geometry::LightView;
use flashmat::infer::{estimate, load_model, load_photo, overhead_camera};
use std::path::PathBuf;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let photo_path = args.get(1).map_or_else(|| flashmat::bundled_root().join("examples/photos/IMG_6950.png"), PathBuf::from);
    let out = PathBuf::from(args.get(2).map_or("out/relight_photo", String::as_str));
    std::fs::create_dir_all(&out)?;

    let loaded = load_model(None, tch::Device::Cpu)?; // the bundled model
    let photo = load_photo(&photo_path, Some(28.0), 256)?; // linear, 256x256, the model's 28-degree view
    let material = estimate(&loaded.model, &loaded.info, &photo)?; // M_est: photo -> neural map
    material.save(&out.join("material.nmat"))?;

    // Four point lights over the material, seen from straight above.
    for (i, light) in [[2.0, 0.0, 3.0], [0.0, 2.0, 3.0], [-2.0, 0.0, 3.0], [0.0, 0.0, 4.0]].into_iter().enumerate() {
        let linear = material.render_image(&LightView { light, view: overhead_camera() })?; // ND_enc + M_render
        flashmat::io::write_png(&out.join(format!("light{i}.png")), &linear.to_display(), flashmat::io::BitDepth::Eight)?;
    }
    println!("wrote {}/material.nmat and light0..3.png", out.display());
    Ok(())
}
