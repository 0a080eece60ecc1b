//! End-to-end checks of `flashmat fit`: the exported folder, the MatFusion
//! layout read back by `flashmat render`, the glTF read back by the `gltf`
//! crate (a maintained glTF 2.0 loader) and re-rendered, and bad inputs
//! (one error line, no partial folder).

use flashmat::fit::export::{from_metallic, DIELECTRIC_F0};
use flashmat::geometry::LightView;
use flashmat::image::Image;
use flashmat::model::{Model, ModelConfig, ModelInfo};
use std::path::{Path, PathBuf};
use tch::{Device, Kind, Tensor};

mod common;
use common::*;

/// A tiny random model and a 32x32 neural material estimated by it from a
/// procedural material's flash render.
fn material(d: &Path) -> (PathBuf, PathBuf, PathBuf) {
    tch::manual_seed(7);
    let model = d.join("tiny.safetensors");
    Model::new(&ModelConfig::tiny(), Device::Cpu).unwrap().save(&model, &ModelInfo { ldr_input: false, steps: 1 }, false).unwrap();
    let m = flashmat::data::procedural::generate(11, &flashmat::data::procedural::ProceduralConfig::with_size(32));
    let photo = d.join("photo.exr");
    flashmat::io::write_exr(&photo, &flashmat::svbrdf::render::render_material(&m, &[LightView::colocated(28.0)]).unwrap()[0]).unwrap();
    let nmat = d.join("m.nmat");
    assert_ok(&flashmat(&["estimate", s(&photo), "--model", s(&model), "--size", "32", "-o", s(&nmat)]));
    (model, photo, nmat)
}

fn read(p: &Path) -> Tensor {
    flashmat::io::read_image(p).unwrap().to_tensor()
}

fn log_diff(a: &Tensor, b: &Tensor) -> f64 {
    (a.log1p() - b.log1p()).abs().mean(Kind::Double).double_value(&[])
}

/// GGX renders `[K, 3, H, W]` of maps `[10, H, W]`.
fn render(maps: &Tensor, configs: &[LightView]) -> Tensor {
    let k = configs.len() as i64;
    let (l, v) = flashmat::geometry::config_tensors(configs, Device::Cpu);
    flashmat::svbrdf::render::render(&maps.unsqueeze(0), &l.view([1, k, 3]), &v.view([1, k, 3])).get(0)
}

fn configs() -> Vec<LightView> {
    vec![LightView::colocated(28.0), LightView { light: [1.5, 1.0, 2.0], view: [0.0, 0.0, 4.0] }, LightView { light: [-1.0, 0.5, 1.5], view: [1.0, -1.0, 3.0] }]
}

#[test]
fn fit_writes_maps_that_flashmat_and_a_gltf_loader_read_back() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (_, _, nmat) = material(d);
    let out = d.join("fit");
    let err = assert_ok(&flashmat(&["fit", s(&nmat), "--steps", "40", "--samples", "16", "-o", s(&out)]));
    assert!(err.contains("fitted GGX in 40 steps over 16 direction pairs") && err.contains("mean error"), "{err}");
    assert_eq!(files_in(&out), ["error.exr", "error.png", "fit.json", "gltf", "maps", "svbrdf"]);
    assert_eq!(files_in(d).iter().filter(|n| n.contains(".tmp-")).count(), 0);

    // fit.json: the mean error is the error map's mean.
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("fit.json")).unwrap()).unwrap();
    let mean = report["fit"]["mean_error"].as_f64().unwrap();
    let error = read(&out.join("error.exr"));
    assert_eq!(error.size(), [1, 32, 32]);
    assert!((error.mean(Kind::Double).double_value(&[]) - mean).abs() < 1e-6, "{mean}");
    assert!(mean <= report["fit"]["mean_error_init"].as_f64().unwrap() + 1e-6);
    assert_eq!((report["width"].as_u64(), report["fit"]["config"]["steps"].as_u64()), (Some(32), Some(40)));

    // The fitted maps (linear EXR) as [10, H, W].
    let m = |name: &str| read(&out.join("maps").join(name));
    let maps = Tensor::cat(&[m("diffuse.exr"), m("specular.exr"), m("roughness.exr"), m("normal.exr")], 0);
    assert_eq!(maps.size(), [10, 32, 32]);
    let norms = maps.narrow(0, 7, 3).square().sum_dim_intlist([0i64].as_slice(), false, Kind::Double).sqrt();
    assert!((norms - 1.0).abs().max().double_value(&[]) < 1e-5);
    // PNG colour maps are sRGB-encoded: decode(png) = exr to 8-bit precision.
    let png = flashmat::io::read_image(&out.join("maps/diffuse.png")).unwrap();
    let exr = flashmat::io::read_image(&out.join("maps/diffuse.exr")).unwrap();
    let worst = png.data.iter().zip(&exr.data).map(|(p, e)| (p - flashmat::spaces::srgb_encode(*e)).abs()).fold(0f32, f32::max);
    assert!(worst <= 0.5 / 255.0 + 1e-6, "{worst}");
    // OpenGL and DirectX normals differ in green only.
    let (gl, dx) = (flashmat::io::read_image(&out.join("maps/normal.png")).unwrap(), flashmat::io::read_image(&out.join("maps/normal_directx.png")).unwrap());
    let px = 32 * 32;
    assert_eq!(gl.data[..px], dx.data[..px]);
    assert!(gl.data[px..2 * px].iter().zip(&dx.data[px..2 * px]).all(|(a, b)| (a + b - 1.0).abs() < 1.5 / 255.0));

    // The MatFusion layout: `flashmat render --svbrdf` renders it as the fitted maps (8-bit maps).
    let r = d.join("r.exr");
    assert_ok(&flashmat(&["render", "--svbrdf", s(&out.join("svbrdf")), "--light", "1.5,1,2", "--view", "0,0,4", "-o", s(&r)]));
    let diff = log_diff(&read(&r), &render(&maps, &configs()[1..2]).get(0));
    eprintln!("svbrdf render vs fitted maps: {diff:.5}");
    assert!(diff < 0.01, "{diff}");

    // The glTF, read back by the gltf crate.
    let (doc, buffers, images) = gltf::import(out.join("gltf/material.gltf")).unwrap();
    assert_eq!(doc.meshes().count(), 1);
    let prim = doc.meshes().next().unwrap().primitives().next().unwrap();
    assert_eq!(prim.mode(), gltf::mesh::Mode::Triangles);
    let reader = prim.reader(|b| Some(&buffers[b.index()]));
    let pos: Vec<[f32; 3]> = reader.read_positions().unwrap().collect();
    let uv: Vec<[f32; 2]> = reader.read_tex_coords(0).unwrap().into_f32().collect();
    let idx: Vec<u32> = reader.read_indices().unwrap().into_u32().collect();
    assert!(reader.read_normals().unwrap().all(|n| n == [0.0, 0.0, 1.0]));
    assert!(reader.read_tangents().unwrap().all(|t| t == [1.0, 0.0, 0.0, 1.0]));
    assert_eq!((pos.len(), idx.len()), (4, 6));
    for (p, t) in pos.iter().zip(&uv) {
        assert_eq!(*t, [(p[0] + 1.0) / 2.0, (1.0 - p[1]) / 2.0], "uv of {p:?}");
    }
    // Both triangles face +z (counter-clockwise seen from the front).
    for tri in idx.chunks(3) {
        let [a, b, c] = [pos[tri[0] as usize], pos[tri[1] as usize], pos[tri[2] as usize]];
        assert!((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]) > 0.0);
    }
    let mat = prim.material();
    let pbr = mat.pbr_metallic_roughness();
    assert_eq!((pbr.base_color_factor(), pbr.metallic_factor(), pbr.roughness_factor()), ([1.0; 4], 1.0, 1.0));
    let texture = |t: gltf::texture::Texture| {
        let im = &images[t.source().index()];
        assert_eq!((im.width, im.height, im.format), (32, 32, gltf::image::Format::R8G8B8));
        im.pixels.clone()
    };
    let base = texture(pbr.base_color_texture().unwrap().texture());
    let mr = texture(pbr.metallic_roughness_texture().unwrap().texture());
    let normal = mat.normal_texture().unwrap();
    assert_eq!(normal.scale(), 1.0);
    let normal = texture(normal.texture());
    // Occlusion: the loader finds the texture, its red channel is maps/ao.png.
    let occlusion = mat.occlusion_texture().unwrap();
    assert_eq!(occlusion.strength(), 1.0);
    let orm = texture(occlusion.texture());
    let ao = flashmat::io::read_image(&out.join("maps/ao.png")).unwrap();
    assert!(ao.data.iter().enumerate().all(|(i, &a)| (orm[i * 3] as f32 / 255.0 - a).abs() < 0.5 / 255.0 + 1e-6));
    assert!(ao.data.iter().all(|&a| a > 0.0 && a <= 1.0));
    // Height: height.png spans fit.json's range, height.exr holds the heights themselves.
    let [lo, hi] = [report["height_range"][0].as_f64().unwrap() as f32, report["height_range"][1].as_f64().unwrap() as f32];
    let (hp, he) = (flashmat::io::read_image(&out.join("maps/height.png")).unwrap(), flashmat::io::read_image(&out.join("maps/height.exr")).unwrap());
    assert!(hi > lo);
    assert!(hp.data.iter().zip(&he.data).all(|(p, e)| (lo + p * (hi - lo) - e).abs() <= (hi - lo) * 1e-4));
    assert!(std::fs::read_to_string(out.join("maps/README.md")).unwrap().contains(&format!("a relief of **{:.6}** plane units", hi - lo)));

    // Re-render the glTF material: each pixel centre's UV from the loader's
    // quad (axis-aligned, so UV is linear in x, y), textures decoded as glTF
    // defines them (base colour sRGB, roughness G, metallic B, normal (2c - 1)),
    // kd = (1 - m) c and ks = 0.04 (1 - m) + m c.
    let lo = pos.iter().fold([f32::MAX; 2], |a, p| [a[0].min(p[0]), a[1].min(p[1])]);
    let hi = pos.iter().fold([f32::MIN; 2], |a, p| [a[0].max(p[0]), a[1].max(p[1])]);
    let corner = |x: f32, y: f32| uv[pos.iter().position(|p| p[0] == x && p[1] == y).unwrap()];
    let (uv00, uv11) = (corner(lo[0], hi[1]), corner(hi[0], lo[1]));
    let n = 32usize;
    let sample = |pix: &[u8], i: usize, j: usize, c: usize| {
        let [x, y, _] = flashmat::geometry::pixel_center(i, j, n, n);
        let (fx, fy) = ((x as f32 - lo[0]) / (hi[0] - lo[0]), (hi[1] - y as f32) / (hi[1] - lo[1]));
        let (u, v) = (uv00[0] + fx * (uv11[0] - uv00[0]), uv00[1] + fy * (uv11[1] - uv00[1]));
        let (col, row) = (((u * n as f32) as usize).min(n - 1), ((v * n as f32) as usize).min(n - 1));
        pix[(row * n + col) * 3 + c] as f32 / 255.0
    };
    let plane = |pix: &[u8], c: usize, f: &dyn Fn(f32) -> f32| Image::from_fn(1, n, n, |_, i, j| f(sample(pix, i, j, c))).to_tensor();
    let rgb = |pix: &[u8], f: &dyn Fn(f32) -> f32| Tensor::cat(&[plane(pix, 0, f), plane(pix, 1, f), plane(pix, 2, f)], 0);
    let base_color = rgb(&base, &flashmat::spaces::srgb_decode);
    let metallic = plane(&mr, 2, &|v| v);
    let roughness = plane(&mr, 1, &|v| v);
    let nrm = rgb(&normal, &|v| 2.0 * v - 1.0);
    let nrm = &nrm / nrm.square().sum_dim_intlist([0i64].as_slice(), true, Kind::Float).sqrt();
    let (kd, ks) = from_metallic(&base_color, &metallic);
    let gltf_maps = Tensor::cat(&[kd, ks, roughness.shallow_clone(), nrm], 0);
    // Roughness is written unchanged (alpha = r^2 on both sides).
    assert!((&roughness - maps.narrow(0, 6, 1)).abs().max().double_value(&[]) <= 0.5 / 255.0 + 1e-6);
    // Where the fit is a plain dielectric (ks = 0.04 grey), glTF's metallic is 0.
    let ks_fit = maps.narrow(0, 3, 3);
    let dielectric = (&ks_fit - DIELECTRIC_F0).abs().amax([0i64].as_slice(), false).lt(0.002);
    if dielectric.any().int64_value(&[]) == 1 {
        assert!(metallic.get(0).masked_select(&dielectric).max().double_value(&[]) <= 1.0 / 255.0);
    }
    let renders = |m: &Tensor| render(m, &configs());
    let diff = log_diff(&renders(&gltf_maps), &renders(&maps));
    let reported = report["gltf_conversion_error"].as_f64().unwrap();
    eprintln!("glTF re-render vs fitted maps: {diff:.5} (fit.json over the fit's pairs: {reported:.5}; fit error {mean:.5})");
    assert!(diff < 0.03, "{diff}");
    assert!(reported < 0.03, "{reported}");

    // Running again replaces the earlier fit.
    assert_ok(&flashmat(&["fit", s(&nmat), "--steps", "1", "--samples", "8", "-o", s(&out)]));
    let again: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("fit.json")).unwrap()).unwrap();
    assert_eq!(again["fit"]["config"]["steps"].as_u64(), Some(1));
}

#[test]
fn fit_estimates_a_photo_first() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (model, photo, _) = material(d);
    let out = d.join("from-photo");
    let err = assert_ok(&flashmat(&["fit", s(&photo), "--model", s(&model), "--size", "32", "--steps", "5", "--samples", "8", "-o", s(&out)]));
    assert!(err.contains("estimated in ") && err.contains("fitted GGX in 5 steps"), "{err}");
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("fit.json")).unwrap()).unwrap();
    assert_eq!(report["width"].as_u64(), Some(32));
    assert!(report["source"].as_str().unwrap().ends_with("photo.exr"));

    // A 3:2 photo fits as a 32 x 48 material; the glTF quad keeps texels square.
    let m = flashmat::data::procedural::generate(12, &flashmat::data::procedural::ProceduralConfig::with_size(48));
    let m = m.crop(8, 0, 32, 48).unwrap();
    let wide = d.join("wide.exr");
    flashmat::io::write_exr(&wide, &flashmat::svbrdf::render::render_material(&m, &[LightView::colocated(28.0)]).unwrap()[0]).unwrap();
    let out = d.join("from-wide");
    assert_ok(&flashmat(&["fit", s(&wide), "--model", s(&model), "--size", "32", "--steps", "2", "--samples", "8", "-o", s(&out)]));
    let report: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("fit.json")).unwrap()).unwrap();
    assert_eq!((report["width"].as_u64(), report["height"].as_u64()), (Some(48), Some(32)));
    let gltf: serde_json::Value = serde_json::from_slice(&std::fs::read(out.join("gltf/material.gltf")).unwrap()).unwrap();
    assert_eq!(gltf["accessors"][0]["max"], serde_json::json!([1.5, 1.0, 0.0]));
    assert_eq!(gltf["accessors"][0]["min"], serde_json::json!([-1.5, -1.0, 0.0]));
}

#[test]
fn bad_inputs_give_one_line_and_leave_no_folder() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (_, _, nmat) = material(d);
    let before = files_in(d);

    // A damaged .nmat (bytes flipped in the middle) and a truncated one.
    let mut bytes = std::fs::read(&nmat).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0xff;
    let bad = d.join("bad.nmat");
    std::fs::write(&bad, &bytes).unwrap();
    assert_error(&flashmat(&["fit", s(&bad), "--steps", "1", "--samples", "8", "-o", s(&d.join("new/out"))]), &["bad.nmat"]);
    let short = d.join("short.nmat");
    std::fs::write(&short, &bytes[..mid]).unwrap();
    assert_error(&flashmat(&["fit", s(&short), "--steps", "1", "--samples", "8", "-o", s(&d.join("out"))]), &["short.nmat"]);
    assert!(!d.join("new").exists() && !d.join("out").exists());

    // An output folder that cannot be created (its parent is a file).
    let blocker = d.join("blocker");
    std::fs::write(&blocker, b"x").unwrap();
    assert_error(&flashmat(&["fit", s(&nmat), "--steps", "1", "--samples", "8", "-o", s(&blocker.join("out"))]), &["cannot create output folder", "blocker"]);
    // A folder holding something else is not overwritten.
    let other = d.join("other");
    std::fs::create_dir(&other).unwrap();
    std::fs::write(other.join("notes.txt"), b"keep me").unwrap();
    assert_error(&flashmat(&["fit", s(&nmat), "--steps", "1", "--samples", "8", "-o", s(&other)]), &["not an earlier fit"]);
    assert_eq!(files_in(&other), ["notes.txt"]);
    // Bad settings.
    assert_error(&flashmat(&["fit", s(&nmat), "--samples", "2", "-o", s(&d.join("out"))]), &["--samples"]);

    let mut after = files_in(d);
    after.retain(|n| !["bad.nmat", "short.nmat", "blocker", "other"].contains(&n.as_str()));
    assert_eq!(after, before, "left behind: {after:?}");
}

/// Whole folders: `estimate DIR -o OUTDIR` with one broken photo writes the
/// others, reports the broken one in one line, ends with the summary and
/// exit code 1; `fit OUTDIR -o FITS` then fits every material; `view` alike.
#[test]
fn batches_go_on_past_a_bad_file() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (model, photo, _) = material(d);
    let photos = d.join("photos");
    std::fs::create_dir(&photos).unwrap();
    std::fs::copy(&photo, photos.join("a.exr")).unwrap();
    std::fs::copy(&photo, photos.join("c.exr")).unwrap();
    std::fs::write(photos.join("b.png"), b"not a png").unwrap();
    std::fs::write(photos.join("notes.txt"), b"skipped: not a photo").unwrap();
    // A folder with a .nmat output is a mistake, refused in one line.
    assert_error(&flashmat(&["estimate", s(&photos), "--model", s(&model), "-o", s(&d.join("x.nmat"))]), &["-o names an output folder, not a .nmat file"]);
    let nmats = d.join("nmats");
    let out = flashmat(&["estimate", s(&photos), "--model", s(&model), "--size", "32", "-o", s(&nmats)]);
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert_eq!(files_in(&nmats), ["a.nmat", "c.nmat"]);
    let failed: Vec<&str> = err.lines().filter(|l| l.starts_with("failed: ")).collect();
    assert_eq!(failed.len(), 1, "{err}");
    assert!(failed[0].contains("b.png"), "{err}");
    let last = err.lines().last().unwrap();
    assert!(last.starts_with("error: estimate: 2 of 3 inputs written to") && last.contains("1 failed") && last.contains("b.png"), "{err}");

    // A file and a folder mixed: one fit folder each, exit 0.
    let more = d.join("more");
    std::fs::create_dir(&more).unwrap();
    std::fs::copy(nmats.join("a.nmat"), more.join("z.nmat")).unwrap();
    let fits = d.join("fits");
    let err = assert_ok(&flashmat(&["fit", s(&more.join("z.nmat")), s(&nmats), "--steps", "5", "--samples", "8", "-o", s(&fits)]));
    assert!(err.lines().last().unwrap().starts_with("fit: 3 of 3 inputs written to"), "{err}");
    assert_eq!(files_in(&fits), ["a", "c", "z"]);
    for f in files_in(&fits) {
        assert!(fits.join(&f).join("fit.json").is_file(), "{f}");
    }
    let pages = d.join("pages");
    assert_ok(&flashmat(&["view", s(&nmats), "-o", s(&pages)]));
    assert_eq!(files_in(&pages), ["a.html", "c.html"]);
}

/// `--tile`: the written material's map wraps around as smoothly as its
/// inside, and says so; `--ao-depth` below 0 is one error line.
#[test]
fn tile_makes_the_written_map_wrap() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (model, photo, nmat) = material(d);
    let tiled = d.join("tiled.nmat");
    let err = assert_ok(&flashmat(&["estimate", s(&photo), "--model", s(&model), "--size", "32", "--tile", "-o", s(&tiled)]));
    assert!(err.contains("tiled: code step across the wrap / inside"), "{err}");
    let map = |p: &Path| flashmat::infer::NeuralMaterial::load(p, Device::Cpu).unwrap().neural_map;
    let (wx, ix, wy, iy) = flashmat::infer::tiling::wrap_steps(&map(&tiled));
    let (wx0, ix0, wy0, iy0) = flashmat::infer::tiling::wrap_steps(&map(&nmat));
    eprintln!("wrap / interior: before {:.2} {:.2}, after {:.2} {:.2}", wx0 / ix0, wy0 / iy0, wx / ix, wy / iy);
    assert!(wx < 2.0 * ix && wy < 2.0 * iy, "{wx} {ix} {wy} {iy}");
    assert_error(&flashmat(&["fit", s(&tiled), "--ao-depth", "-1", "-o", s(&d.join("f"))]), &["--ao-depth must be a finite number >= 0"]);
}
