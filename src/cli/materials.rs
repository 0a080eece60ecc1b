//! `flashmat render` and `flashmat svbrdf generate|preview`.

use super::{light_view, prepare_output, CapturesArgs, GenerateArgs, MaterialArgs, PreviewArgs, RenderArgs, Renderer};
use flashmat::data::loaders::{load_readable, open_dataset, unreadable_error, write_material_dir, write_matfusion, Unreadable};
use flashmat::data::procedural::{self, Family, ProceduralConfig};
use flashmat::geometry::LightView;
use flashmat::image::Image;
use flashmat::svbrdf::cpu;
use flashmat::svbrdf::height::ensure_height_field;
use flashmat::svbrdf::render::{render_material, render_material_shadowed};
use flashmat::svbrdf::shadow::ShadowOptions;
use flashmat::svbrdf::{encode_normal_map, Svbrdf};
use anyhow::{bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;

/// Resolves a `--svbrdf` source to a named material.
pub fn load_material(args: &MaterialArgs) -> Result<(String, Svbrdf)> {
    check_material_size("--size", args.size)?;
    if let Some(i) = procedural::parse_test_material(&args.source)? {
        return Ok((format!("test{i:02}"), procedural::test_material(i, args.size)));
    }
    if let Some(rest) = args.source.strip_prefix("procedural:") {
        let mut parts = rest.split(':');
        let seed: u64 = parts.next().unwrap_or("").parse().with_context(|| format!("'{}': expected procedural:SEED or procedural:SEED:FAMILY", args.source))?;
        let material = match parts.next() {
            Some(family) => {
                let family: Family = family.parse().map_err(|e| anyhow::anyhow!("{e}"))?;
                procedural::generate_family(family, seed, args.size)
            }
            None => procedural::generate(seed, &ProceduralConfig { size: args.size, ..Default::default() }),
        };
        return Ok((format!("procedural-{seed}"), material));
    }
    let dataset = open_dataset(std::path::Path::new(&args.source))?;
    if args.index >= dataset.len() {
        bail!("--index {} is out of range: {} holds {} material(s)", args.index, args.source, dataset.len());
    }
    Ok((dataset.name(args.index), dataset.load(args.index)?))
}

/// Checks the side of a material to generate: at least 1 pixel, at most
/// [`flashmat::limits::MATERIAL_SIZE`].
fn check_material_size(option: &str, size: usize) -> Result<()> {
    anyhow::ensure!(size >= 1, "{option} must be at least 1 pixel");
    flashmat::limits::MATERIAL_SIZE.check(option, size as u64)
}

/// Writes a linear render: EXR keeps radiance, PNG gets the sRGB curve (`Image::to_display`).
pub fn write_render(path: &std::path::Path, linear: &Image) -> Result<()> {
    let out_dir = prepare_output(path)?;
    match path.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase()).as_deref() {
        Some("exr") => flashmat::io::write_exr(path, linear)?,
        Some("png") => flashmat::io::write_png(path, &linear.to_display(), flashmat::io::BitDepth::Eight)?,
        _ => bail!("{}: output must end in .png or .exr", path.display()),
    }
    out_dir.keep();
    Ok(())
}

pub fn render(args: &RenderArgs) -> Result<()> {
    let config = light_view(args.light, args.view)?;
    let shadows = ShadowOptions { height_scale: args.height_scale, light_radius: args.light_radius, light_samples: args.light_samples };
    shadows.validate()?;
    let (_, mut material) = load_material(&args.material)?;
    if let Some(rows) = args.rows {
        let (h, w) = (material.height(), material.width());
        anyhow::ensure!(rows >= 1 && rows <= h && w <= 4 * rows, "--rows must be between {} and the material's {h} rows, got {rows}", w.div_ceil(4));
        material = material.crop((h - rows) / 2, 0, rows, w)?;
    }
    let start = std::time::Instant::now();
    if args.shadows {
        ensure_height_field(&mut material)?;
    }
    let integrated = start.elapsed();
    let start = std::time::Instant::now();
    let image = match (args.renderer, args.shadows) {
        (Renderer::Tensor, false) => render_material(&material, &[config])?.remove(0),
        (Renderer::Tensor, true) => render_material_shadowed(&material, &[config], &shadows)?.remove(0),
        (Renderer::Cpu, shadowed) => {
            let data = if shadowed { cpu::render_shadowed(&material, &[config], &shadows)? } else { cpu::render(&material, &[config]) };
            Image::from_data(3, material.height(), material.width(), data)?
        }
    };
    let elapsed = start.elapsed();
    write_render(&args.output, &image)?;
    let what = if args.shadows { format!(" with shadows (height field ready in {:.1} ms)", integrated.as_secs_f64() * 1e3) } else { String::new() };
    eprintln!("wrote {} ({:?} renderer, {:.1} ms{what})", args.output.display(), args.renderer, elapsed.as_secs_f64() * 1e3);
    Ok(())
}

pub fn generate(args: &GenerateArgs) -> Result<()> {
    check_material_size("--size", args.size)?;
    flashmat::limits::COUNT.check("--count", args.count as u64)?;
    std::fs::create_dir_all(&args.out).with_context(|| format!("cannot create {}", args.out.display()))?;
    let seeds: Vec<u64> = if args.test_set {
        procedural::test_seeds()
    } else {
        (args.start..args.start + args.count as u64).map(procedural::training_seed).collect()
    };
    let bar = ProgressBar::new(seeds.len() as u64).with_style(ProgressStyle::with_template("{bar:40} {pos}/{len} materials {per_sec} ETA {eta}")?);
    let cfg = ProceduralConfig { size: args.size, ..Default::default() };
    seeds.par_iter().enumerate().try_for_each(|(i, &seed)| -> Result<()> {
        let m = procedural::generate(seed, &cfg);
        if args.test_set {
            write_material_dir(&args.out.join(format!("test-{i:02}")), &m)?;
        } else {
            write_matfusion(&args.out, args.start as usize + i + 1, &m)?;
        }
        bar.inc(1);
        Ok(())
    })?;
    bar.finish();
    eprintln!("wrote {} materials to {}", seeds.len(), args.out.display());
    Ok(())
}

/// One preview row: diffuse, specular, roughness, normals (display-encoded), co-located render.
pub fn preview_row(material: &Svbrdf, size: usize) -> Result<Vec<Image>> {
    let render = render_material(material, &[LightView::colocated(flashmat::geometry::MODEL_FOV_DEG)])?.remove(0);
    let cells = [
        material.diffuse.to_display(),
        material.specular.to_display(),
        material.roughness.clone(),
        encode_normal_map(&material.normal),
        render.to_display(),
    ];
    Ok(cells.iter().map(|c| c.resize_bilinear(size, size)).collect())
}

pub fn preview(args: &PreviewArgs) -> Result<()> {
    check_material_size("--size", args.size)?;
    // The grid holds every cell: count x 5 cells of size^2 pixels.
    flashmat::limits::IMAGE_PIXELS.check_product(format_args!("the preview grid (--count {} x 5 cells of --size {} squared)", args.count, args.size), &[args.count as u64, 5, args.size as u64, args.size as u64])?;
    let out_dir = prepare_output(&args.output)?;
    // A dataset material that cannot be read is left out of the grid, named, and fails the command at the end.
    let (materials, skipped): (Vec<Svbrdf>, Vec<Unreadable>) = match args.source.as_str() {
        "procedural" => {
            let seeds: Vec<u64> = (0..args.count as u64).map(procedural::training_seed).collect();
            (procedural::generate_many(&seeds, 256), vec![])
        }
        "procedural-test" => (procedural::generate_many(&procedural::test_seeds()[..args.count.min(50)], 256), vec![]),
        path => {
            let ds = open_dataset(std::path::Path::new(path))?;
            let (read, skipped) = load_readable(ds.as_ref(), args.count, Ok)?;
            (read.into_iter().map(|(_, m)| m).collect(), skipped)
        }
    };
    let rows: Vec<Vec<Image>> = materials.par_iter().map(|m| preview_row(m, args.size)).collect::<Result<_>>()?;
    let grid = flashmat::viz::grid(&rows, 4)?;
    flashmat::io::write_png(&args.output, &grid, flashmat::io::BitDepth::Eight)?;
    out_dir.keep();
    let left_out = if skipped.is_empty() {
        String::new()
    } else {
        format!("; left out, unreadable: {}", skipped.iter().map(|u| u.name.as_str()).collect::<Vec<_>>().join(", "))
    };
    eprintln!("wrote {} ({} materials: diffuse | specular | roughness | normals | co-located render{left_out})", args.output.display(), rows.len());
    if !skipped.is_empty() {
        return Err(unreadable_error(&skipped, rows.len() + skipped.len()));
    }
    Ok(())
}

/// `flashmat svbrdf captures`: a synthetic capture folder of one material
/// (square-cropped and resized to --size).
pub fn captures(args: &CapturesArgs) -> Result<()> {
    if args.photos < 2 {
        bail!("--photos must be at least 2 (one to estimate from, others to compare with), got {}", args.photos);
    }
    flashmat::limits::COUNT.check("--photos", args.photos as u64)?;
    flashmat::infer::photo::check_size(args.material.size)?;
    let (name, material) = load_material(&args.material)?;
    let material = flashmat::eval::fit_to_size(&material, args.material.size)?;
    let configs = flashmat::data::captures::synthetic_configs(args.photos);
    flashmat::data::captures::write_synthetic(&args.output, &material, &configs, args.sample_width)?;
    println!("wrote {} photos of {name} with their positions to {}", configs.len(), args.output.display());
    Ok(())
}
