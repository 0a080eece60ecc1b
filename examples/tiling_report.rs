//! The seam figures of reports/tiling.md: a material's map repeated 2x2
//! (as a tiled floor repeats it), rendered under the flash and under moved
//! lights; the mean |ln(1 + R)| step between neighbouring pixels across the
//! wrap-around lines against the mean step between all other neighbours
//! (ratio 1: the wrap is no more visible than any interior pixel pair).
//! Also writes a picture (JPEG, halved): the first material repeated 3x3
//! beside the last one repeated 3x3 (pass the untiled material last).
//!
//! A `flashmat fit` folder in place of a .nmat: its fitted GGX maps
//! (maps/*.exr), repeated and rendered the same way by the GGX renderer.
//!
//! cargo run --release --example tiling_report -- OUT.jpg A.nmat|FITDIR [B.nmat|FITDIR ...]
use flashmat::geometry::LightView;
use flashmat::infer::NeuralMaterial;
use tch::{Device, Kind, Tensor};

/// The map `[C, H, W]` repeated n x n.
fn repeated(map: &Tensor, n: i64) -> Tensor {
    map.repeat([1, n, n])
}

/// (wrap step, interior step) of renders `[K, 3, 2H, 2W]` of a 2x2 repeat.
fn steps(r: &Tensor, h: i64, w: i64) -> (f64, f64) {
    let l = r.log1p().to_kind(Kind::Double);
    let dx = (l.narrow(3, 1, 2 * w - 1) - l.narrow(3, 0, 2 * w - 1)).abs().mean_dim([0i64, 1].as_slice(), false, Kind::Double); // [2H, 2W-1]
    let dy = (l.narrow(2, 1, 2 * h - 1) - l.narrow(2, 0, 2 * h - 1)).abs().mean_dim([0i64, 1].as_slice(), false, Kind::Double); // [2H-1, 2W]
    let wrap = (dx.select(1, w - 1).sum(Kind::Double) + dy.select(0, h - 1).sum(Kind::Double)).double_value(&[]) / (2 * h + 2 * w) as f64;
    let all = dx.sum(Kind::Double).double_value(&[]) + dy.sum(Kind::Double).double_value(&[]);
    let interior = (all - wrap * (2 * h + 2 * w) as f64) / ((2 * h * (2 * w - 1) + (2 * h - 1) * 2 * w) - (2 * h + 2 * w)) as f64;
    (wrap, interior)
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    anyhow::ensure!(args.len() >= 2, "usage: tiling_report OUT.jpg A.nmat [B.nmat ...]");
    let flash = NeuralMaterial::identity_config();
    let view = flash.view;
    let lights = [("flash", flash), ("light 1.5,1,2", LightView { light: [1.5, 1.0, 2.0], view }), ("light -1.2,-0.8,1.5", LightView { light: [-1.2, -0.8, 1.5], view })];
    println!("| material | light | wrap / interior step | interior step |");
    println!("|---|---|---|---|");
    for path in args[1..].iter().filter(|p| std::path::Path::new(p).is_dir()) {
        let read = |n: &str| flashmat::io::read_image(&std::path::Path::new(path).join("maps").join(n)).map(|i| i.to_tensor());
        let maps = Tensor::cat(&[read("diffuse.exr")?, read("specular.exr")?, read("roughness.exr")?, read("normal.exr")?], 0); // [10, H, W]
        let (h, w) = (maps.size()[1], maps.size()[2]);
        let big = repeated(&maps, 2).unsqueeze(0);
        for (name, lv) in &lights {
            let (l, v) = flashmat::geometry::config_tensors(&[*lv], Device::Cpu);
            let r = flashmat::svbrdf::render::render(&big, &l.view([1, 1, 3]), &v.view([1, 1, 3])).get(0); // [1, 3, 2H, 2W]
            let (wrap, interior) = steps(&r, h, w);
            println!("| {path} (fitted GGX) | {name} | {:.2} | {interior:.4} |", wrap / interior);
        }
    }
    let args: Vec<String> = args.into_iter().filter(|p| !std::path::Path::new(p).is_dir()).collect();
    for path in &args[1..] {
        let mut m = NeuralMaterial::load(std::path::Path::new(path), Device::Cpu)?;
        let map = m.neural_map.shallow_clone();
        let (h, w) = (map.size()[1], map.size()[2]);
        m.neural_map = repeated(&map, 2);
        for (name, lv) in &lights {
            let r = m.render(&[*lv])?; // [1, 3, 2H, 2W]
            let (wrap, interior) = steps(&r, h, w);
            println!("| {path} | {name} | {:.2} | {interior:.4} |", wrap / interior);
        }
    }
    let picture = |path: &str| -> anyhow::Result<Tensor> {
        let mut m = NeuralMaterial::load(std::path::Path::new(path), Device::Cpu)?;
        m.neural_map = repeated(&m.neural_map, 3);
        Ok(m.render_image(&lights[1].1)?.to_display().to_tensor()) // [3, 3H, 3W]
    };
    let (first, last) = (picture(&args[1])?, picture(args.last().expect("checked"))?);
    let gap = Tensor::ones([3, first.size()[1], 8], (Kind::Float, Device::Cpu));
    let both = Tensor::cat(&[first, gap, last], 2).unsqueeze(0).avg_pool2d([2, 2], [2, 2], [0, 0], false, true, None::<i64>).get(0);
    let (out, both) = (std::path::Path::new(&args[0]), flashmat::image::Image::from_tensor(&both)?);
    match out.extension().and_then(|e| e.to_str()) {
        Some("png") => flashmat::io::write_png(out, &both, flashmat::io::BitDepth::Eight)?,
        _ => flashmat::io::write_jpeg(out, &both, 80)?,
    }
    Ok(())
}
