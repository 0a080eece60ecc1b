//! The covered-photo check (`fit::coverage`, issue 85) on capture folders:
//! each held-out material's synthetic capture (`flashmat svbrdf captures`'
//! photos, 8-bit, with fall-off) loaded as `estimate --capture` loads it,
//! clean and with photo 01's left half painted one grey (a card over the
//! sample). Prints one line a material and the counts; the frame's path is
//! `scripts/coverage_scan.sh`.
//!
//! ```sh
//! cargo run --release --example coverage_folders -- [PHOTOS=3,5] [SIZE=256] [MATERIALS=0-49]
//! ```

use anyhow::{Context, Result};
use flashmat::data::captures::{synthetic_configs, write_synthetic, Captures};
use flashmat::fit::photos::load_capture;

fn main() -> Result<()> {
    tch::set_num_threads(1);
    let args: Vec<String> = std::env::args().skip(1).collect();
    let arg = |i: usize| args.get(i).filter(|a| a.as_str() != "-");
    let counts: Vec<usize> = arg(0).map_or("3,5", |s| s.as_str()).split(',').map(|s| s.parse()).collect::<Result<_, _>>()?;
    let size: usize = arg(1).map(|s| s.parse()).transpose()?.unwrap_or(256);
    let (a, b) = arg(2).map_or("0-49", |s| s.as_str()).split_once('-').context("MATERIALS as A-B")?;
    let (first, last): (usize, usize) = (a.parse()?, b.parse()?);
    for &photos in &counts {
        let (mut clean_refused, mut carded_named, mut n) = (0, 0, 0);
        for m in first..=last {
            let dir = tempfile::tempdir()?;
            let d = dir.path();
            write_synthetic(d, &flashmat::data::procedural::test_material(m, size), &synthetic_configs(photos), 10.0)?;
            let clean = load_capture(&Captures::open(d)?, photos, size).err().map(|e| format!("{e:#}"));
            let mut photo = flashmat::io::read_rgb(&d.join("01.png"))?;
            let (h, w) = (photo.height, photo.width);
            for c in 0..3 {
                for y in 0..h {
                    photo.data[(c * h + y) * w..(c * h + y) * w + w / 2].fill(0.35);
                }
            }
            flashmat::io::write_png(&d.join("01.png"), &photo, flashmat::io::BitDepth::Eight)?;
            let carded = load_capture(&Captures::open(d)?, photos, size).err().map(|e| format!("{e:#}"));
            n += 1;
            clean_refused += clean.is_some() as usize;
            carded_named += carded.as_deref().is_some_and(|e| e.starts_with("01.png: ") && e.contains("is flat in it")) as usize;
            println!("test{m:02}, {photos} photos | clean: {} | carded: {}", clean.as_deref().unwrap_or("accepted"), carded.as_deref().unwrap_or("accepted"));
        }
        println!("materials {n}, photos {photos}, {size}x{size}: clean captures refused {clean_refused}, carded photo named {carded_named}");
    }
    Ok(())
}
