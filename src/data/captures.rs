//! Capture folders of one flat material: photos `NN.png` (numbered;
//! sorted by number), `camera_pos.txt` and `light_pos.txt` (one `x,y,z` per
//! line, one line per photo, in photo order) and `image_size.txt` (the
//! sample's width: the unit of the positions), and optionally
//! `exposures.txt` (one number per line, per photo: the light each photo's
//! sensor gathered, in any unit, e.g. exposure time x ISO / f-number^2; or
//! three, R,G,B, when the white balance changed too;
//! bracketed photos of one position record a highlight's peak that the
//! longer exposure clips). The origin is the sample
//! centre, x points right and y up in the photos, z out of the sample;
//! photos are rectified to the sample square.
//!
//! Positions are converted to flashmat units, where the material spans
//! [-1, 1]: divided by width / 2. Photos hold the light's 1/r^2 fall-off,
//! which the renderers omit: [`Captures::load_compensated`] multiplies each
//! photo by |light - p|^2 / r0^2 per surface point p, with r0 the overhead
//! light's distance to the sample centre (so the input photo keeps its
//! level at the centre). `eval::captures` scores methods on such folders;
//! `fit::photos` (`estimate --capture`) fits one material to all their photos.
//!
//! [`write_synthetic`] writes such a folder from a GGX material (the
//! fall-off applied), for trying the format and for tests.

use crate::geometry::{fov_to_distance, length, pixel_positions, LightView, MODEL_FOV_DEG};
use crate::image::Image;
use crate::svbrdf::Svbrdf;
use anyhow::{anyhow, bail, ensure, Result};
use std::path::{Path, PathBuf};
use tch::{Device, Kind, Tensor};

/// Smallest photo side accepted, in pixels (LPIPS needs 31).
const MIN_PHOTO_SIDE: usize = 32;

/// How far from square a rectified photo may be (relative).
const SQUARE_TOLERANCE: f64 = 0.02;

/// One capture folder, parsed and checked.
#[derive(Clone, Debug, PartialEq)]
pub struct Captures {
    pub dir: PathBuf,
    /// Photos sorted by their number.
    pub photos: Vec<PathBuf>,
    /// Camera positions, flashmat units, one per photo.
    pub cameras: Vec<[f64; 3]>,
    /// Light positions, flashmat units, one per photo.
    pub lights: Vec<[f64; 3]>,
    /// The sample's width in the files' unit.
    pub sample_width: f64,
    /// Each photo's exposure per channel, R, G, B ([`EXPOSURES_FILE`]: one
    /// number a line for all three, or three; all 1 without the file).
    pub exposures: Vec<[f64; 3]>,
    /// Each photo's gain to a normal exposure: a RAW photo's
    /// 2^BaselineExposure (`io::raw_baseline_gain`), 1 for 8-bit photos.
    pub raw_gains: Vec<f64>,
}

/// Distances of a capture's lights and cameras from the sample's centre
/// that [`Captures::open`] takes, in flashmat units (half sample widths).
pub const POSITION_DISTANCES: std::ops::RangeInclusive<f64> = 0.5..=1000.0;

/// The optional file of the photos' exposures in a capture folder.
pub const EXPOSURES_FILE: &str = "exposures.txt";

impl Captures {
    /// Reads and checks a capture folder. Errors are one line naming the
    /// file at fault.
    pub fn open(dir: &Path) -> Result<Self> {
        ensure!(dir.is_dir(), "capture folder {} does not exist", dir.display());
        let (numbers, photos) = numbered_photos(dir)?;
        let size_path = dir.join("image_size.txt");
        let size_text = read_text(&size_path)?;
        let sample_width: f64 = size_text
            .trim()
            .parse()
            .map_err(|_| anyhow!("{}: expected one number (the sample's width), got '{}'", size_path.display(), size_text.trim()))?;
        ensure!(sample_width.is_finite() && sample_width > 0.0, "{}: the sample's width must be > 0, got {sample_width}", size_path.display());
        let scale = 2.0 / sample_width;
        // Line n of each position file belongs to photo n: with gaps in the
        // numbering the files keep a line for every number up to the last.
        let lines = numbers.last().map_or(0, |&n| n as usize + 1);
        let gaps = lines != photos.len();
        let by_number = |values: Vec<[f64; 3]>| numbers.iter().map(|&n| values[n as usize]).collect::<Vec<_>>();
        let with_gaps = |e: anyhow::Error| if gaps { anyhow!("{e}; the photos are numbered with gaps ({} missing), and line n belongs to photo n", missing_numbers(&numbers)) } else { e };
        let needs = if gaps { format!("photos numbered up to {:02} need {lines}", lines - 1) } else { format!("the folder has {lines} photos") };
        let cameras = by_number(read_positions(&dir.join("camera_pos.txt"), scale, lines, &needs).map_err(with_gaps)?);
        let lights = by_number(read_positions(&dir.join("light_pos.txt"), scale, lines, &needs).map_err(with_gaps)?);
        // In half sample widths (the sample spans -1 to 1): a phone over a
        // hand-sized sample is 2-20 away. Far outside, the width and the
        // positions are in different units (or the width is mistyped).
        for (file, positions) in [("camera_pos.txt", &cameras), ("light_pos.txt", &lights)] {
            for (p, number) in positions.iter().zip(&numbers) {
                let d = length(*p);
                ensure!(
                    POSITION_DISTANCES.contains(&d),
                    "{}: photo {number:02} is {:.3e} sample widths from the sample (image_size.txt: the sample is {sample_width:?} wide), outside {}-{}: are the width and the positions in one unit?",
                    dir.join(file).display(),
                    d / 2.0,
                    POSITION_DISTANCES.start() / 2.0,
                    POSITION_DISTANCES.end() / 2.0
                );
            }
        }
        let exposures_path = dir.join(EXPOSURES_FILE);
        let exposures = if exposures_path.exists() {
            let all = read_exposures(&exposures_path, lines, &needs).map_err(with_gaps)?;
            numbers.iter().map(|&n| all[n as usize]).collect()
        } else {
            vec![[1.0; 3]; photos.len()]
        };
        let raw_gains = photos.iter().map(|p| crate::io::raw_baseline_gain(p)).collect();
        Ok(Self { dir: dir.to_path_buf(), photos, cameras, lights, sample_width, exposures, raw_gains })
    }

    /// The factors, R, G, B, that bring photo `i`'s linear values to photo
    /// `reference`'s exposure and white balance (its [`EXPOSURES_FILE`] line
    /// over `i`'s) and to a normal exposure (`i`'s RAW gain).
    pub fn exposure_factor(&self, i: usize, reference: usize) -> [f64; 3] {
        std::array::from_fn(|c| self.exposures[reference][c] / self.exposures[i][c] * self.raw_gains[i])
    }

    /// Index of the photo taken closest to straight overhead: the camera
    /// with the smallest angle to +z (the first one on ties).
    pub fn overhead(&self) -> usize {
        overhead_index(&self.cameras)
    }

    /// Light and camera of photo `i`, flashmat units.
    pub fn config(&self, i: usize) -> LightView {
        LightView { light: self.lights[i], view: self.cameras[i] }
    }

    /// r0: distance of the overhead photo's light to the sample centre,
    /// flashmat units; photos are compensated to this distance.
    pub fn reference_distance(&self) -> f64 {
        length(self.lights[self.overhead()])
    }

    /// Every photo at `size x size`, linear (decoded with ^2.2), with
    /// the 1/r^2 fall-off compensated (see the module docs) and brought to
    /// the overhead photo's exposure: `[3, S, S]` each.
    pub fn load_compensated(&self, size: usize) -> Result<Vec<Tensor>> {
        let r0 = self.reference_distance();
        (0..self.photos.len())
            .map(|i| Ok(compensated(&load_photo(&self.photos[i], size)?, self.lights[i], r0, self.exposure_factor(i, self.overhead()))))
            .collect()
    }
}

/// Index of the camera with the smallest angle to +z (the first on ties).
pub fn overhead_index(cameras: &[[f64; 3]]) -> usize {
    let cos = |c: &[f64; 3]| c[2] / length(*c);
    let mut best = 0;
    for (i, c) in cameras.iter().enumerate() {
        if cos(c) > cos(&cameras[best]) {
            best = i;
        }
    }
    best
}

/// Light fall-off relative to distance r0: r0^2 / |light - p|^2 for each
/// pixel's surface point p of an H x W photo of the [-1,1]^2 sample.
/// Returns `[1, H, W]` (CPU, float).
pub fn falloff(light: [f64; 3], r0: f64, h: usize, w: usize) -> Tensor {
    let p = pixel_positions(h, w, (Kind::Float, Device::Cpu));
    let l = Tensor::from_slice(&light.map(|c| c as f32)).view([3, 1, 1]);
    let r2 = (l - p).square().sum_dim_intlist([0i64].as_slice(), true, Kind::Float);
    r2.reciprocal() * (r0 * r0)
}

/// A photo as the fit sees it: divided by its flash's fall-off relative to
/// distance r0 ([`falloff`]) and brought to the reference exposure
/// (`exposure_ratio`: the reference's exposure over the photo's, per channel).
/// photo: linear `[3, H, W]` (CPU) -> `[3, H, W]`.
pub fn compensated(photo: &Tensor, light: [f64; 3], r0: f64, exposure_ratio: [f64; 3]) -> Tensor {
    let s = photo.size();
    let ratio = Tensor::from_slice(&exposure_ratio.map(|v| v as f32)).view([3, 1, 1]).to_device(photo.device());
    photo / falloff(light, r0, s[1] as usize, s[2] as usize) * ratio
}

/// One capture photo, linear `[3, S, S]`: gamma-decoded (^2.2, as every
/// 8-bit photo flashmat reads; a RAW photo is linear already, 1 at its
/// white level) and resized to `size` (area when shrinking, bilinear when
/// enlarging). Refuses photos that are not square (they
/// should be rectified to the sample square) or smaller than 32 pixels.
pub fn load_photo(path: &Path, size: usize) -> Result<Tensor> {
    Ok(load_photo_sized(path, size)?.0)
}

/// [`load_photo`] and the photo's own (width, height) before resizing.
pub fn load_photo_sized(path: &Path, size: usize) -> Result<(Tensor, (usize, usize))> {
    let (image, format) = crate::io::read_image_with_format(path)?;
    ensure!(format.clips_at_one(), "{}: a capture photo is an 8-bit or RAW photo, not HDR", path.display());
    let rgb = crate::io::to_rgb(&image);
    let (w, h) = (rgb.width, rgb.height);
    ensure!(
        w.min(h) >= MIN_PHOTO_SIDE,
        "{}: the photo is {w}x{h} pixels; capture photos need at least {MIN_PHOTO_SIDE}x{MIN_PHOTO_SIDE}",
        path.display()
    );
    ensure!(
        (w as f64 - h as f64).abs() <= SQUARE_TOLERANCE * w.max(h) as f64,
        "{}: the photo is {w}x{h} pixels, not square; capture photos must be rectified to the sample square",
        path.display()
    );
    let linear = if format.is_float() { rgb } else { rgb.map(crate::spaces::gamma_decode) };
    Ok((linear.resize_to(size, size).to_tensor(), (w, h)))
}

fn read_text(path: &Path) -> Result<String> {
    std::fs::read_to_string(path).map_err(|e| anyhow!("cannot read {}: {e}", path.display()))
}

/// Extensions of capture photos: 8-bit, ^2.2-encoded files (a phone's
/// JPEGs, or PNGs), or linear DNGs (the `raw` feature).
const PHOTO_EXTENSIONS: [&str; 4] = ["png", "jpg", "jpeg", "dng"];

/// `NN.png` / `NN.jpg` / `NN.dng` files of `dir` sorted by number; errors when there are none.
fn numbered_photos(dir: &Path) -> Result<(Vec<u64>, Vec<PathBuf>)> {
    let mut found: Vec<(u64, PathBuf)> = Vec::new();
    for p in crate::io::sorted_entries(dir)? {
        let is_photo = p.extension().and_then(|e| e.to_str()).is_some_and(|e| PHOTO_EXTENSIONS.iter().any(|x| e.eq_ignore_ascii_case(x)));
        if let (true, Some(n)) = (is_photo, p.file_stem().and_then(|s| s.to_str()).and_then(|s| s.parse::<u64>().ok())) {
            found.push((n, p));
        }
    }
    ensure!(!found.is_empty(), "no numbered photos (00.png or 00.jpg, 01.png ...) in capture folder {}", dir.display());
    found.sort();
    if let Some(w) = found.windows(2).find(|w| w[0].0 == w[1].0) {
        bail!("capture folder {}: photos {} and {} have the same number", dir.display(), w[0].1.display(), w[1].1.display());
    }
    // A number far past the photos would ask for that many position lines.
    let last = found.last().map_or(0, |(n, _)| *n);
    ensure!(last < 10 * found.len() as u64 + 100, "capture folder {}: photo {} is numbered far past the {} photos (number them 00, 01, ... in order)", dir.display(), found.last().map_or(String::new(), |(_, p)| p.display().to_string()), found.len());
    Ok(found.into_iter().unzip())
}

/// The numbers below the last of `numbers` (sorted) that no photo has, as
/// "02, 05-06".
fn missing_numbers(numbers: &[u64]) -> String {
    let mut out: Vec<String> = vec![];
    let mut expected = 0;
    for &n in numbers {
        if n > expected {
            out.push(if n - 1 == expected { format!("{expected:02}") } else { format!("{expected:02}-{:02}", n - 1) });
        }
        expected = n + 1;
    }
    out.join(", ")
}

/// Parses one `x,y,z` per non-empty line, scaled by `scale`; there must be
/// `expected` lines and every z must be > 0.
fn read_positions(path: &Path, scale: f64, expected: usize, needs: &str) -> Result<Vec<[f64; 3]>> {
    let text = read_text(path)?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let v = crate::geometry::parse_position(line).map_err(|e| anyhow!("{} line {}: {e}", path.display(), i + 1))?;
        ensure!(v[2] > 0.0, "{} line {}: z must be > 0 (above the sample), got '{}'", path.display(), i + 1, line.trim());
        out.push(v.map(|c| c * scale));
    }
    ensure!(
        out.len() == expected,
        "{} has {} positions but {needs} (one line per photo)",
        path.display(),
        out.len()
    );
    Ok(out)
}

/// Parses one exposure per non-empty line (one number, or three: R,G,B): `expected` of them, finite and > 0.
fn read_exposures(path: &Path, expected: usize, needs: &str) -> Result<Vec<[f64; 3]>> {
    let text = read_text(path)?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let bad = || anyhow!("{} line {}: expected one number (the photo's exposure) or three (R,G,B), got '{}'", path.display(), i + 1, line.trim());
        let values: Vec<f64> = line.split([',', ' ', '\t']).filter(|v| !v.is_empty()).map(|v| v.parse::<f64>().map_err(|_| bad())).collect::<Result<_>>()?;
        let v: [f64; 3] = match values[..] {
            [v] => [v; 3],
            [r, g, b] => [r, g, b],
            _ => return Err(bad()),
        };
        ensure!(v.iter().all(|v| v.is_finite() && *v > 0.0), "{} line {}: an exposure must be a finite number > 0, got '{}'", path.display(), i + 1, line.trim());
        out.push(v);
    }
    ensure!(out.len() == expected, "{} has {} exposures but {needs} (one line per photo)", path.display(), out.len());
    let (low, high) = out.iter().flatten().fold((f64::INFINITY, 0.0f64), |(l, h), &v| (l.min(v), h.max(v)));
    ensure!(
        high / low <= MAX_EXPOSURE_RATIO,
        "{}: its exposures span {:.1e}x ({low:?} to {high:?}), more than the {MAX_EXPOSURE_RATIO}x (10 stops) one capture's photos can differ by and still show one material; correct the file",
        path.display(),
        high / low
    );
    Ok(out)
}

/// The most two photos of one capture may differ in exposure: 10 stops
/// (bracketing spans 2-6; a photo 10 stops under its neighbour is black).
pub const MAX_EXPOSURE_RATIO: f64 = 1024.0;

/// Co-located phone positions after the overhead photo (flashmat units:
/// the sample spans [-1, 1]) whose flash reflections land half-way to the
/// edge in the sample's four quarters: the two, then two more
/// (`flashmat bench capture`, `examples/capture_highlights`).
pub const TILTED_PHONES: [[f64; 3]; 4] = [[0.9, -0.7, 3.7], [-0.8, 0.9, 3.8], [0.85, 0.8, 3.6], [-0.9, -0.75, 3.7]];

/// Co-located flash configurations of a synthetic capture (a phone with
/// its flash): photo 0 straight overhead at the model's camera distance,
/// then `count - 1` around the sample at the same distance, elevations 65,
/// 50 and 35 degrees in turn, azimuths evenly spread.
pub fn synthetic_configs(count: usize) -> Vec<LightView> {
    let d = fov_to_distance(MODEL_FOV_DEG);
    let mut out = vec![LightView::colocated(MODEL_FOV_DEG)];
    let others = count.saturating_sub(1);
    for i in 0..others {
        let elevation = [65.0f64, 50.0, 35.0][i % 3].to_radians();
        let azimuth = 2.0 * std::f64::consts::PI * i as f64 / others as f64;
        let p = [d * elevation.cos() * azimuth.cos(), d * elevation.cos() * azimuth.sin(), d * elevation.sin()];
        out.push(LightView { light: p, view: p });
    }
    out.truncate(count);
    out
}

/// Writes a capture folder of a GGX material (CPU renderer): 8-bit
/// photos `NN.png` (display-encoded, with the 1/r^2 fall-off relative to
/// the overhead light, see [`Captures::reference_distance`]), the
/// positions in units of `sample_width` and `image_size.txt`.
/// configs: flashmat units, at least one.
pub fn write_synthetic(dir: &Path, material: &Svbrdf, configs: &[LightView], sample_width: f64) -> Result<()> {
    write_synthetic_exposed(dir, material, configs, &vec![1.0; configs.len()], sample_width)
}

/// [`write_synthetic`] with each photo's linear values scaled by its
/// exposure (one per config) before the 8-bit encoding, and
/// [`EXPOSURES_FILE`] written when they are not all 1: bracketed photos.
pub fn write_synthetic_exposed(dir: &Path, material: &Svbrdf, configs: &[LightView], exposures: &[f64], sample_width: f64) -> Result<()> {
    write_synthetic_as(dir, material, configs, exposures, sample_width, PhotoFiles::Png8)
}

/// How [`write_synthetic_as`] stores the photos.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum PhotoFiles {
    /// `NN.png`, 8-bit, ^2.2-encoded: highlights clip at 1.
    Png8,
    /// `NN.dng`, linear, `bits` bits a sample, as a phone's RAW with
    /// headroom: the brightest value of all photos at 0.95 of the white
    /// level (nothing clips), BaselineExposure bringing it back; but the
    /// normal exposure's white at most `max_headroom_stops` under the
    /// sensor's (what is brighter clips, as on a phone that exposes for the
    /// diffuse; `f64::INFINITY`: nothing clips).
    Dng { bits: u32, max_headroom_stops: f64 },
}

/// [`write_synthetic_exposed`] with the photos stored as `files` says.
pub fn write_synthetic_as(dir: &Path, material: &Svbrdf, configs: &[LightView], exposures: &[f64], sample_width: f64, files: PhotoFiles) -> Result<()> {
    ensure!(!configs.is_empty(), "a capture needs at least one photo");
    ensure!(exposures.len() == configs.len() && exposures.iter().all(|e| e.is_finite() && *e > 0.0), "one exposure > 0 per photo");
    ensure!(sample_width.is_finite() && sample_width > 0.0, "the sample's width must be > 0, got {sample_width}");
    for c in configs {
        ensure!(c.light[2] > 0.0 && c.view[2] > 0.0, "capture positions must be above the sample (z > 0)");
    }
    std::fs::create_dir_all(dir).map_err(|e| anyhow!("cannot create capture folder {}: {e}", dir.display()))?;
    let (h, w) = (material.height(), material.width());
    let cameras: Vec<[f64; 3]> = configs.iter().map(|c| c.view).collect();
    let r0 = length(configs[overhead_index(&cameras)].light);
    let renders = crate::svbrdf::cpu::render_tensor(material, configs);
    let linear: Vec<Tensor> = configs.iter().enumerate().map(|(i, c)| renders.get(i as i64) * falloff(c.light, r0, h, w) * exposures[i]).collect();
    let peak = linear.iter().map(|l| l.max().double_value(&[])).fold(1e-6, f64::max);
    for (i, linear) in linear.iter().enumerate() {
        match files {
            PhotoFiles::Png8 => {
                // Capture folders are ^2.2-encoded (read with `gamma_decode`),
                // unlike flashmat's other pictures.
                let display = Image::from_tensor(&crate::spaces::linear_to_display(linear))?;
                crate::io::write_png(&dir.join(format!("{i:02}.png")), &display, crate::io::BitDepth::Eight)?;
            }
            PhotoFiles::Dng { bits, max_headroom_stops } => {
                let headroom = (0.95 / peak).max(0.5f64.powf(max_headroom_stops));
                let opts = crate::io::dng::DngOptions { bits, baseline_exposure: -headroom.log2(), ..Default::default() };
                crate::io::dng::write_dng(&dir.join(format!("{i:02}.dng")), &Image::from_tensor(&(linear * headroom))?, &opts)?;
            }
        }
    }
    let unit = sample_width / 2.0;
    let lines = |pick: fn(&LightView) -> [f64; 3]| -> String {
        configs.iter().map(|c| pick(c).map(|v| v * unit)).map(|p| format!("{:.6},{:.6},{:.6}\n", p[0], p[1], p[2])).collect()
    };
    crate::io::atomic_write_bytes(&dir.join("camera_pos.txt"), lines(|c| c.view).as_bytes())?;
    crate::io::atomic_write_bytes(&dir.join("light_pos.txt"), lines(|c| c.light).as_bytes())?;
    if exposures.iter().any(|&e| e != 1.0) {
        let lines: String = exposures.iter().map(|e| format!("{e}\n")).collect();
        crate::io::atomic_write_bytes(&dir.join(EXPOSURES_FILE), lines.as_bytes())?;
    }
    crate::io::atomic_write_bytes(&dir.join("image_size.txt"), format!("{sample_width}\n").as_bytes())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn falloff_is_r0_squared_over_r_squared() {
        // 2x2 pixels: centres at (+-0.5, +-0.5, 0); light at (0, 0, 2),
        // r^2 = 0.25 + 0.25 + 4 = 4.5 everywhere, r0 = 2: 4 / 4.5.
        let f = falloff([0.0, 0.0, 2.0], 2.0, 2, 2);
        assert_eq!(f.size(), vec![1, 2, 2]);
        for v in Vec::<f32>::try_from(f.flatten(0, -1)).unwrap() {
            assert!((v - 4.0 / 4.5).abs() < 1e-6, "{v}");
        }
        // Light at (1, 0, 1): the right column (x = 0.5) is nearer, r^2 =
        // 0.25 + 0.25 + 1 = 1.5; the left one r^2 = 2.25 + 0.25 + 1 = 3.5.
        let f = falloff([1.0, 0.0, 1.0], 1.0, 2, 2);
        assert!((f.double_value(&[0, 0, 1]) - 1.0 / 1.5).abs() < 1e-6);
        assert!((f.double_value(&[0, 1, 0]) - 1.0 / 3.5).abs() < 1e-6);
    }

    fn fixture(dir: &Path, photos: usize, cams: &str, lights: &str, size: &str) {
        for i in 0..photos {
            crate::io::write_png(&dir.join(format!("{i:02}.png")), &crate::image::Image::filled(3, 4, 4, 0.5), crate::io::BitDepth::Eight)
                .unwrap();
        }
        std::fs::write(dir.join("camera_pos.txt"), cams).unwrap();
        std::fs::write(dir.join("light_pos.txt"), lights).unwrap();
        std::fs::write(dir.join("image_size.txt"), size).unwrap();
    }

    fn err(dir: &Path) -> String {
        let m = format!("{:#}", Captures::open(dir).unwrap_err());
        assert!(!m.contains('\n'), "{m}");
        m
    }

    #[test]
    fn parses_a_capture_folder() {
        let t = tempfile::tempdir().unwrap();
        fixture(t.path(), 3, "10,0,40\n0, 1 ,50\n-20,5,30\n", "10,0,40\n0,1,50\n-20,5,30\n\n", "20\n");
        let c = Captures::open(t.path()).unwrap();
        assert_eq!(c.photos.len(), 3);
        assert!(c.photos[2].ends_with("02.png"));
        assert_eq!(c.sample_width, 20.0);
        // Divided by width / 2 = 10.
        assert_eq!(c.cameras[0], [1.0, 0.0, 4.0]);
        assert_eq!(c.lights[2], [-2.0, 0.5, 3.0]);
        assert_eq!(c.overhead(), 1);
    }

    #[test]
    fn synthetic_configs_are_colocated_flash_photos() {
        let c = synthetic_configs(7);
        assert_eq!(c.len(), 7);
        let d = fov_to_distance(MODEL_FOV_DEG);
        assert_eq!(c[0], LightView::colocated(MODEL_FOV_DEG));
        for (i, x) in c.iter().enumerate().skip(1) {
            assert_eq!(x.light, x.view);
            assert!((length(x.view) - d).abs() < 1e-9);
            let elevation = (x.view[2] / d).asin().to_degrees();
            assert!((elevation - [65.0, 50.0, 35.0][(i - 1) % 3]).abs() < 1e-9, "{elevation}");
        }
        assert_eq!(overhead_index(&c.iter().map(|x| x.view).collect::<Vec<_>>()), 0);
        assert_eq!(synthetic_configs(1).len(), 1);
    }

    #[test]
    fn synthetic_captures_round_trip_to_the_renderer() {
        // Photos written with the fall-off, read back and compensated, are
        // the renderer's images (up to 8-bit rounding of display values).
        let t = tempfile::tempdir().unwrap();
        let material = crate::data::procedural::test_material(3, 32);
        let configs = synthetic_configs(4);
        write_synthetic(t.path(), &material, &configs, 8.0).unwrap();
        let c = Captures::open(t.path()).unwrap();
        assert_eq!(c.photos.len(), 4);
        assert_eq!(c.sample_width, 8.0);
        for (a, b) in c.cameras.iter().zip(&configs) {
            for k in 0..3 {
                assert!((a[k] - b.view[k]).abs() < 1e-5, "{a:?} vs {:?}", b.view);
            }
        }
        assert_eq!(c.overhead(), 0);
        assert!((c.reference_distance() - fov_to_distance(MODEL_FOV_DEG)).abs() < 1e-5);
        let photos = c.load_compensated(32).unwrap();
        let truth = crate::eval::reference_renders(&material, &configs);
        let disp = crate::spaces::linear_to_display;
        for (i, p) in photos.iter().enumerate() {
            let err = (disp(p) - disp(&truth.get(i as i64))).abs().max().double_value(&[]);
            assert!(err < 1.5 / 255.0 + 1e-4, "photo {i}: display error {err}");
        }
        // Uncompensated, the oblique photos are darker where the light is
        // far: at the pixel farthest from photo 3's light the raw photo is
        // the render times r0^2 / r^2 < 1.
        let raw = load_photo(&c.photos[3], 32).unwrap();
        let f = falloff(c.lights[3], c.reference_distance(), 32, 32);
        let fmin = f.min().double_value(&[]);
        assert!(fmin < 0.75, "{fmin}");
        let lin_err = (&raw - truth.get(3) * &f).abs().max().double_value(&[]);
        assert!(lin_err < 0.02, "{lin_err}");
    }

    #[test]
    fn bracketed_photos_are_brought_to_the_overhead_photos_exposure() {
        // Photo 1 four stops darker (1/16): read back it is photo 0 again
        // wherever neither clips, within the darker one's 8-bit steps; the
        // longer exposure's clipped highlight is there, unclipped, in the short one.
        let t = tempfile::tempdir().unwrap();
        let material = crate::data::procedural::test_material(5, 32);
        let overhead = LightView::colocated(MODEL_FOV_DEG);
        write_synthetic_exposed(t.path(), &material, &[overhead, overhead], &[1.0, 0.0625], 8.0).unwrap();
        let c = Captures::open(t.path()).unwrap();
        assert_eq!(c.exposures, [[1.0; 3], [0.0625; 3]]);
        let photos = c.load_compensated(32).unwrap();
        let truth = crate::eval::reference_renders(&material, &[overhead]).get(0);
        let peak = truth.max().double_value(&[]);
        assert!(peak > 1.5, "the test material's highlight clips at exposure 1 (peak {peak})");
        assert_eq!(load_photo(&c.photos[0], 32).unwrap().max().double_value(&[]), 1.0, "photo 0 clips");
        assert!((photos[1].max().double_value(&[]) / peak - 1.0).abs() < 0.05, "{} vs {peak}", photos[1].max().double_value(&[]));
        // Where photo 0 is mid-grey, the darker photo's 8-bit steps are 4-9% of the value.
        let mid = photos[0].gt(0.1).logical_and(&photos[0].lt(0.5));
        let rel = ((&photos[1] - &photos[0]).abs() / &photos[0]).masked_select(&mid).mean(Kind::Double).double_value(&[]);
        assert!(rel < 0.04, "mean relative difference {rel}");
        // Bad files are one line naming them.
        std::fs::write(t.path().join(EXPOSURES_FILE), "1\n").unwrap();
        assert!(err(t.path()).contains("exposures.txt has 1 exposures but the folder has 2 photos"));
        std::fs::write(t.path().join(EXPOSURES_FILE), "1\n-0.5\n").unwrap();
        assert!(err(t.path()).contains("exposures.txt line 2: an exposure must be a finite number > 0"));
        std::fs::write(t.path().join(EXPOSURES_FILE), "1\nbright\n").unwrap();
        assert!(err(t.path()).contains("exposures.txt line 2: expected one number"));
        std::fs::write(t.path().join(EXPOSURES_FILE), "1\n0.5,1\n").unwrap();
        assert!(err(t.path()).contains("exposures.txt line 2: expected one number (the photo's exposure) or three (R,G,B)"));
        // Three numbers a line: a white balance too (`flashmat capture`'s light meter).
        std::fs::write(t.path().join(EXPOSURES_FILE), "1\n0.5,1,2\n").unwrap();
        assert_eq!(Captures::open(t.path()).unwrap().exposures, [[1.0; 3], [0.5, 1.0, 2.0]]);
        std::fs::write(t.path().join(EXPOSURES_FILE), "1\n1e300\n").unwrap();
        assert!(err(t.path()).contains("exposures.txt: its exposures span 1.0e300x"), "{}", err(t.path()));
        // 10 stops is still a capture.
        std::fs::write(t.path().join(EXPOSURES_FILE), "1\n0.0009765625\n").unwrap();
        assert_eq!(Captures::open(t.path()).unwrap().exposures, [[1.0; 3], [1.0 / 1024.0; 3]]);
        std::fs::remove_file(t.path().join(EXPOSURES_FILE)).unwrap();
        assert_eq!(Captures::open(t.path()).unwrap().exposures, [[1.0; 3], [1.0; 3]]);
    }

    #[test]
    fn a_phones_jpegs_are_capture_photos_decoded_as_the_pngs() {
        let t = tempfile::tempdir().unwrap();
        fixture(t.path(), 2, "0,0,4\n0,0,5\n", "0,0,4\n0,0,5\n", "2");
        // 01 as a JPEG of the same grey: read in number order, decoded with the same curve.
        let grey = crate::image::Image::filled(3, 32, 32, 0.5);
        crate::io::write_png(&t.path().join("00.png"), &grey, crate::io::BitDepth::Eight).unwrap();
        std::fs::remove_file(t.path().join("01.png")).unwrap();
        crate::io::write_jpeg(&t.path().join("01.jpg"), &grey, 95).unwrap();
        let c = Captures::open(t.path()).unwrap();
        let names: Vec<String> = c.photos.iter().map(|p| p.file_name().unwrap().to_string_lossy().into_owned()).collect();
        assert_eq!(names, ["00.png", "01.jpg"]);
        let (png, _) = load_photo_sized(&c.photos[0], 32).unwrap();
        let (jpg, _) = load_photo_sized(&c.photos[1], 32).unwrap();
        // 0.5 display is 0.5^2.2 = 0.2176 linear; a JPEG of a flat grey keeps it within a code step.
        assert!((png.mean(Kind::Double).double_value(&[]) - 0.2176).abs() < 0.002);
        assert!((jpg.mean(Kind::Double).double_value(&[]) - 0.2176).abs() < 0.005);
        // 01.png beside 01.jpg: two photos with one number.
        crate::io::write_png(&t.path().join("01.png"), &grey, crate::io::BitDepth::Eight).unwrap();
        assert!(err(t.path()).contains("have the same number"));
    }

    #[test]
    fn photos_numbered_with_gaps_take_the_lines_of_their_numbers() {
        // Photos 00, 01, 03 (02 deleted, as a user deletes a blurred one):
        // line n of the position files is photo n's.
        let t = tempfile::tempdir().unwrap();
        fixture(t.path(), 4, "0,0,4\n0,0,5\n0,0,6\n0,0,7\n", "0,0,4\n0,0,5\n0,0,6\n0,0,7\n", "2");
        std::fs::remove_file(t.path().join("02.png")).unwrap();
        let c = Captures::open(t.path()).unwrap();
        // Sample width 2: positions unscaled; photo 03 at z 7, not 6.
        assert_eq!(c.cameras.iter().map(|p| p[2]).collect::<Vec<_>>(), [4.0, 5.0, 7.0]);
        assert_eq!(c.lights[2][2], 7.0);
        // Files with one line per photo (3) are ambiguous: refused, naming the gap.
        std::fs::write(t.path().join("camera_pos.txt"), "0,0,4\n0,0,5\n0,0,7\n").unwrap();
        let m = err(t.path());
        assert!(m.contains("camera_pos.txt has 3 positions but photos numbered up to 03 need 4") && m.contains("numbered with gaps (02 missing)"), "{m}");
        assert!(!m.contains('\n'), "one line: {m}");
        // Exposures follow the numbers too.
        std::fs::write(t.path().join("camera_pos.txt"), "0,0,4\n0,0,5\n0,0,6\n0,0,7\n").unwrap();
        std::fs::write(t.path().join(EXPOSURES_FILE), "1\n2\n3\n4\n").unwrap();
        assert_eq!(Captures::open(t.path()).unwrap().exposures, [[1.0; 3], [2.0; 3], [4.0; 3]]);
        // The gaps' names: single numbers and runs.
        assert_eq!(missing_numbers(&[0, 1, 3, 4, 7]), "02, 05-06");
        assert_eq!(missing_numbers(&[2]), "00-01");
        assert_eq!(missing_numbers(&[0, 1]), "");
        // A number far past the photos is refused before any file is read.
        std::fs::rename(t.path().join("03.png"), t.path().join("999.png")).unwrap();
        assert!(err(t.path()).contains("is numbered far past the 3 photos"));
    }

    #[test]
    fn rejects_inconsistent_folders() {
        let t = tempfile::tempdir().unwrap();
        fixture(t.path(), 3, "0,0,4\n0,0,5\n", "0,0,4\n0,0,5\n0,0,6\n", "2");
        assert!(err(t.path()).contains("camera_pos.txt has 2 positions but the folder has 3 photos"));

        let t = tempfile::tempdir().unwrap();
        fixture(t.path(), 2, "0,0,4\n0,x,5\n", "0,0,4\n0,0,5\n", "2");
        let m = err(t.path());
        assert!(m.contains("camera_pos.txt line 2") && m.contains("not a number"), "{m}");

        let t = tempfile::tempdir().unwrap();
        fixture(t.path(), 2, "0,0,4\n0,0,5\n", "0,0,4\n0,0,5\n", "wide");
        assert!(err(t.path()).contains("image_size.txt: expected one number"));

        let t = tempfile::tempdir().unwrap();
        fixture(t.path(), 2, "0,0,4\n0,0,5\n", "0,0,4\n0,0,-5\n", "2");
        assert!(err(t.path()).contains("light_pos.txt line 2: z must be > 0"));

        // A width in other units than the positions (1e-30: positions of 1e31 half-widths).
        let t = tempfile::tempdir().unwrap();
        fixture(t.path(), 2, "0,0,40\n0,0,50\n", "0,0,40\n0,0,50\n", "1e-30");
        let m = err(t.path());
        assert!(m.contains("camera_pos.txt: photo 00 is 4.000e31 sample widths") && m.contains("one unit"), "{m}");

        let t = tempfile::tempdir().unwrap();
        fixture(t.path(), 2, "0,0,4\n0,0,5\n", "0,0,4\n0,0,5\n", "2");
        std::fs::remove_file(t.path().join("light_pos.txt")).unwrap();
        assert!(err(t.path()).contains("cannot read") && err(t.path()).contains("light_pos.txt"));

        let t = tempfile::tempdir().unwrap();
        assert!(err(t.path()).contains("no numbered photos"));
        assert!(err(&t.path().join("nope")).contains("does not exist"));
    }
}
