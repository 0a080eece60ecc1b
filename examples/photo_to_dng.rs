//! A JPEG or PNG photo as the DNG a phone would have saved beside it: its
//! codes sRGB-decoded to linear light and stored as a 12-bit DNG through
//! `io::dng` (linear, or a Bayer mosaic with `bayer`), with a white balance
//! (neutral 0.5, 1, 0.7) and, with `shaded`, a lens-shading gain map that
//! darkens the corners to half. Read back with the `raw` feature, it should
//! give the photo again: how the RAW path is shown in docs/CAPTURE.md and
//! tried from the command line (`flashmat estimate OUT.dng`).
//!
//! ```sh
//! cargo run --release --features raw --example photo_to_dng -- PHOTO OUT.dng [linear|bayer] [shaded]
//! ```

use anyhow::{ensure, Result};
use flashmat::io::dng::{write_dng, DngOptions};
use std::path::Path;

fn main() -> Result<()> {
    let args: Vec<String> = std::env::args().collect();
    ensure!(args.len() >= 3, "usage: photo_to_dng PHOTO OUT.dng [linear|bayer] [shaded]");
    let bayer = args.get(3).is_some_and(|a| a == "bayer");
    let shaded = args.get(4).is_some_and(|a| a == "shaded");
    let rgb = flashmat::io::read_rgb(Path::new(&args[1]))?;
    // Even sides for the mosaic.
    let (w, h) = (rgb.width / 2 * 2, rgb.height / 2 * 2);
    let linear = flashmat::image::Image::from_fn(3, h, w, |c, y, x| flashmat::spaces::photo_decode(rgb.get(c, y, x)));
    let gain_map = shaded.then(|| (3, 3, vec![2.0, 1.4, 2.0, 1.4, 1.0, 1.4, 2.0, 1.4, 2.0]));
    write_dng(Path::new(&args[2]), &linear, &DngOptions { bayer, gain_map, ..Default::default() })?;
    println!("wrote {} ({w}x{h}, {}{})", args[2], if bayer { "Bayer" } else { "linear" }, if shaded { ", shaded" } else { "" });
    Ok(())
}
