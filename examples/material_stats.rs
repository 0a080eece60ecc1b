//! Shares of the procedural training stream's pixels by kind: dark
//! dielectrics (diffuse luminance below 0.05, F0 below 0.1; the
//! uniform-colour check's near-black materials), bare metal (F0 of at least
//! 0.3), and the rest, each split by roughness, over N training materials.
//!
//! cargo run --release --example material_stats -- [N] [SIZE]
use flashmat::data::procedural::{generate_many, training_seed};

fn main() {
    let args: Vec<String> = std::env::args().collect();
    // One error line and a non-zero exit for bad arguments, never a backtrace.
    let (Ok(count), Ok(size)) = (args.get(1).map_or(Ok(400u64), |s| s.parse()), args.get(2).map_or(Ok(64usize), |s| s.parse())) else {
        eprintln!("material_stats: N and SIZE must be whole numbers (usage: material_stats [N] [SIZE])");
        std::process::exit(2);
    };
    if count == 0 || size == 0 {
        eprintln!("material_stats: N and SIZE must be at least 1");
        std::process::exit(2);
    }
    let seeds: Vec<u64> = (0..count).map(training_seed).collect();
    let materials = generate_many(&seeds, size);
    // [kind][rough]: pixel counts; kinds: dark dielectric, metal, other.
    let mut pixels = [[0u64; 2]; 3];
    let mut materials_with_dark = 0;
    for m in &materials {
        let mut dark_here = 0;
        for i in 0..size * size {
            let lum = |im: &flashmat::image::Image| (0..3).map(|c| im.plane(c)[i]).sum::<f32>() / 3.0;
            let (kd, ks, r) = (lum(&m.diffuse), lum(&m.specular), m.roughness.plane(0)[i]);
            let kind = if kd < 0.05 && ks < 0.1 { 0 } else if ks >= 0.3 { 1 } else { 2 };
            pixels[kind][(r > 0.5) as usize] += 1;
            dark_here += (kind == 0) as usize;
        }
        materials_with_dark += (dark_here * 2 > size * size) as usize;
    }
    let total = (count as usize * size * size) as f64;
    for (name, row) in ["dark dielectric", "metal", "other"].iter().zip(pixels) {
        println!("{name:16} {:6.2}% of pixels (roughness > 0.5: {:6.2}%)", 100.0 * (row[0] + row[1]) as f64 / total, 100.0 * row[1] as f64 / total);
    }
    println!("materials mostly dark dielectric: {materials_with_dark} of {count}");
}
