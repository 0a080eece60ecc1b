//! SVBRDF datasets on disk: readers for three layouts, writers for them, and
//! crops. Every loader returns linear maps (see [`Svbrdf`]):
//!
//! - 8-bit/16-bit PNG (or JPEG) diffuse and specular maps are gamma-encoded
//!   and are linearised with ^2.2 ([`gamma_decode`]); EXR ones are already
//!   linear and are taken as they are;
//! - roughness is linear; a gray or RGB file gives its first channel;
//! - normal maps hold (n + 1) / 2 in [0, 1] (in EXR files too) and are
//!   decoded with [`decode_normal_map`]; short normals are normalised, the
//!   zero vector (as the file stores it) is refused.
//!
//! Layouts:
//! - MatFusion/INRIA training folders ([`MatfusionDataset`]):
//!   `ROOT/{diffuse,specular,roughness,normals}/NNNNNNN_{diffuse,...}.png`
//!   with a 1-based 7-digit index;
//! - per-material folders ([`MaterialDirsDataset`]):
//!   `ROOT/NAME/{diffuse,specular,roughness,normals}.png` (or ROOT itself);
//! - INRIA strips ([`StripDataset`]): one PNG of square panels side by side,
//!   `normal | diffuse | roughness | specular` (width 4H) or
//!   `render | normal | diffuse | roughness | specular` (width 5H).

use crate::image::Image;
use crate::io::{self, BitDepth, FileFormat};
use crate::spaces::{gamma_decode, gamma_encode};
use crate::svbrdf::{decode_normal_map, encode_normal_map, Svbrdf};
use anyhow::{anyhow, bail, Result};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// A list of materials, indexed `0..len()`, in a deterministic order (sorted
/// by name). Shared by training (random access from worker threads) and
/// evaluation.
pub trait SvbrdfSource: Send + Sync {
    /// Number of materials.
    fn len(&self) -> usize;
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// A short human-readable name of material `i` (index, folder or file
    /// name). Panics if `i >= len()`.
    fn name(&self, i: usize) -> String;
    /// Loads material `i` with linear maps, all `H x W`. Errors (naming the
    /// file) for missing, unreadable or inconsistent maps.
    fn load(&self, i: usize) -> Result<Svbrdf>;
    /// [`SvbrdfSource::load`] with the material's name leading its error,
    /// for callers drawing from many (training): `material NAME: ...`.
    fn load_named(&self, i: usize) -> Result<Svbrdf> {
        self.load(i).map_err(|e| if i < self.len() { anyhow!("material {}: {e:#}", self.name(i)) } else { e })
    }
}

/// The four stored maps, in the order used throughout this module.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Map {
    Diffuse,
    Specular,
    Roughness,
    Normals,
}

impl Map {
    const ALL: [Map; 4] = [Map::Diffuse, Map::Specular, Map::Roughness, Map::Normals];

    /// Folder and file-name stem of the map in both folder layouts.
    fn name(self) -> &'static str {
        match self {
            Map::Diffuse => "diffuse",
            Map::Specular => "specular",
            Map::Roughness => "roughness",
            Map::Normals => "normals",
        }
    }
}

/// Map file extensions, in order of preference when several exist.
const MAP_EXTENSIONS: [&str; 4] = ["png", "exr", "jpg", "jpeg"];

fn extension_rank(path: &Path) -> Option<usize> {
    let ext = path.extension()?.to_str()?.to_ascii_lowercase();
    MAP_EXTENSIONS.iter().position(|e| *e == ext)
}

/// How far outside [0, 1] a float map's albedo or roughness may stray
/// (rounding in whatever wrote it) before the map is refused; values
/// within it are clamped.
pub const MAP_RANGE_SLACK: f32 = 0.01;

/// The first value of `image` outside `[lo, hi]` widened by
/// [`MAP_RANGE_SLACK`] (or NaN), as an error naming the map, the file and
/// the place.
fn check_range(image: &Image, lo: f32, hi: f32, what: &str, path: &Path) -> Result<()> {
    let n = image.height * image.width;
    let within = lo - MAP_RANGE_SLACK..=hi + MAP_RANGE_SLACK;
    if let Some(i) = image.data.iter().position(|v| !within.contains(v)) {
        let (c, y, x) = (i / n, (i % n) / image.width, i % image.width);
        bail!("{what} map {} has the value {} at row {y}, column {x}, channel {c}: {what} values lie in [{lo}, {hi}]", path.display(), image.data[i]);
    }
    Ok(())
}

/// Roughness below the data's floor ([`crate::data::procedural::MIN_ROUGHNESS`]) by more than half
/// an 8-bit code: GGX's highlight degenerates at 0 (NaN where the half
/// vector meets the normal) and the networks never saw it. Raised to the
/// floor, with one warning per process (a dataset has many such maps).
fn raise_roughness(rough: &mut Image, path: &Path) {
    let floor = crate::data::procedural::MIN_ROUGHNESS;
    let below = rough.data.iter().filter(|&&v| v < floor - 0.5 / 255.0).count();
    if below == 0 {
        return;
    }
    rough.data.iter_mut().for_each(|v| *v = v.max(floor));
    static WARNED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
    if !WARNED.swap(true, std::sync::atomic::Ordering::Relaxed) {
        eprintln!(
            "warning: roughness map {}: {below} of its {} values are below the minimum roughness {floor} and were raised to it (other maps like it: in silence)",
            path.display(),
            rough.data.len()
        );
    }
}

/// Converts one stored map to its linear `Svbrdf` form (see the module
/// docs). Values no material has are refused with one line naming the
/// file: albedos and roughness outside [0, 1] (float files can hold any
/// value: -1, 1e30), NaN, normals of no direction; roughness below the
/// floor is raised to it ([`raise_roughness`]) and short normals are
/// normalised ([`warn_short_normals`]).
fn decode_map(map: Map, image: Image, format: FileFormat, path: &Path) -> Result<Image> {
    Ok(match map {
        Map::Diffuse | Map::Specular => {
            let rgb = io::to_rgb(&image);
            if format.is_float() {
                check_range(&rgb, 0.0, 1.0, map.name(), path)?;
                rgb.map(|v| v.clamp(0.0, 1.0))
            } else {
                rgb.map(gamma_decode)
            }
        }
        Map::Roughness => {
            let mut rough = io::first_channel(&image);
            check_range(&rough, 0.0, 1.0, "roughness", path)?;
            rough.data.iter_mut().for_each(|v| *v = v.min(1.0));
            raise_roughness(&mut rough, path);
            rough
        }
        Map::Normals => {
            if image.channels < 3 {
                bail!("normal map {} has {} channel(s), expected RGB", path.display(), image.channels);
            }
            let encoded = image.channel_range(0, 3)?;
            let n = encoded.height * encoded.width;
            let at = |i: usize| (i / encoded.width, i % encoded.width, [0, 1, 2].map(|c| encoded.data[c * n + i]));
            // The readers refuse NaN/Inf already; a NaN would slip through
            // the comparisons below, so it is refused here too.
            if let Some(i) = (0..3 * n).find(|&i| !encoded.data[i].is_finite()) {
                let (y, x, rgb) = at(i % n);
                bail!("normal map {} holds a NaN/Inf value at row {y}, column {x} (encoded {rgb:?})", path.display());
            }
            if format.is_float() {
                // Integer files cannot leave [0, 1]; a float file that does
                // probably stores raw vectors, which we do not guess at.
                let (lo, hi) = encoded.data.iter().fold((f32::MAX, f32::MIN), |(l, h), &v| (l.min(v), h.max(v)));
                if lo < -1e-3 || hi > 1.0 + 1e-3 {
                    bail!(
                        "normal map {} has values in [{lo}, {hi}], expected the (n + 1) / 2 encoding in [0, 1]",
                        path.display()
                    );
                }
            }
            let min_length = if format.is_float() { MIN_FLOAT_NORMAL } else { MIN_CODED_NORMAL };
            let length = |i: usize| {
                let v = [0, 1, 2].map(|c| 2.0 * encoded.data[c * n + i] - 1.0);
                (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
            };
            if let Some(i) = (0..n).find(|&i| length(i) < min_length) {
                let (y, x, rgb) = at(i);
                bail!(
                    "normal map {} holds a zero-length normal at row {y}, column {x} (encoded {rgb:?}; a normal map stores (n + 1) / 2 of unit normals)",
                    path.display()
                );
            }
            warn_short_normals((0..n).filter(|&i| length(i) < SHORT_NORMAL).count(), n, path);
            decode_normal_map(&encoded)
        }
    })
}

/// Shortest decoded normal (2 x code - 1) of an integer file that is not
/// the zero vector: an 8-bit file cannot store (0.5, 0.5, 0.5), and its
/// grey pixel (128, 128, 128) decodes to (1, 1, 1) / 255, of length
/// sqrt(3) / 255 = 0.0068; the next shortest it can store are
/// sqrt(11) / 255 = 0.013 and longer. One 8-bit code step, 2 / 255, lies
/// between: shorter is zero as the file stores it (16-bit files, with
/// finer steps, are held to the coarsest encoding's).
const MIN_CODED_NORMAL: f32 = 2.0 / 255.0;

/// The same for float files, which store 0.5 exactly: a few f32 steps at
/// 0.5 (6e-8 each) around the zero vector, whose direction is rounding.
const MIN_FLOAT_NORMAL: f32 = 1e-6;

/// Decoded normals shorter than this are counted in a warning: a normal
/// map stores unit normals, and short ones (probably a tool's averaging or
/// blending) are normalised like any other, but a user may want to know.
const SHORT_NORMAL: f32 = 0.1;

/// One warning per process (a dataset has many such maps), with the count
/// of the first map that has short normals.
fn warn_short_normals(short: usize, total: usize, path: &Path) {
    static WARNED: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);
    if short > 0 && !WARNED.swap(true, std::sync::atomic::Ordering::Relaxed) {
        eprintln!(
            "warning: normal map {}: {short} of {total} normals were shorter than {SHORT_NORMAL} and were normalised (other maps like it: in silence)",
            path.display()
        );
    }
}

/// Loads a material from its four map files (diffuse, specular, roughness,
/// normals); `None` is a missing file, reported with `expected` paths.
fn load_maps(files: [Option<&Path>; 4], expected: impl Fn(Map) -> PathBuf) -> Result<Svbrdf> {
    let mut maps: Vec<(Image, PathBuf)> = Vec::with_capacity(4);
    for (map, file) in Map::ALL.into_iter().zip(files) {
        let Some(path) = file else {
            bail!("missing {} map {}", map.name(), expected(map).display());
        };
        let (image, format) = io::read_image_with_format(path)?;
        let image = decode_map(map, image, format, path)?;
        if let Some((first, first_path)) = maps.first() {
            if (image.height, image.width) != (first.height, first.width) {
                bail!(
                    "{} is {}x{} but {} is {}x{}: the maps of a material must have one size",
                    path.display(),
                    image.width,
                    image.height,
                    first_path.display(),
                    first.width,
                    first.height
                );
            }
        }
        maps.push((image, path.to_path_buf()));
    }
    let mut it = maps.into_iter().map(|(im, _)| im);
    let mut next = || it.next().expect("four maps");
    let s = Svbrdf { diffuse: next(), specular: next(), roughness: next(), normal: next(), height_field: None };
    s.validate()?;
    Ok(s)
}

// ---------------------------------------------------------------- MatFusion

/// The MatFusion/INRIA training layout:
/// `ROOT/diffuse/0000001_diffuse.png`, `ROOT/specular/0000001_specular.png`,
/// `ROOT/roughness/0000001_roughness.png`, `ROOT/normals/0000001_normals.png`
/// (`.exr` and `.jpg` accepted too). Materials are the union of the indices
/// found in the four folders, sorted numerically; one whose map is absent
/// fails to load with the missing file's name.
pub struct MatfusionDataset {
    root: PathBuf,
    /// Index and the four map files (None where absent), sorted by index.
    materials: Vec<(u64, [Option<PathBuf>; 4])>,
}

/// `0000001_diffuse.png` -> Some(1) for map "diffuse".
fn parse_matfusion_name(path: &Path, map: Map) -> Option<u64> {
    extension_rank(path)?;
    let stem = path.file_stem()?.to_str()?;
    let digits = stem.strip_suffix(map.name())?.strip_suffix('_')?;
    if digits.is_empty() || !digits.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    digits.parse().ok()
}

impl MatfusionDataset {
    /// Scans the four map folders (each listed once; no file is opened).
    pub fn open(root: &Path) -> Result<Self> {
        let mut found: BTreeMap<u64, [Option<PathBuf>; 4]> = BTreeMap::new();
        for (k, map) in Map::ALL.into_iter().enumerate() {
            let dir = root.join(map.name());
            if !dir.is_dir() {
                bail!("MatFusion dataset {} has no {}/ folder", root.display(), map.name());
            }
            for path in io::sorted_entries(&dir)? {
                let Some(index) = parse_matfusion_name(&path, map) else { continue };
                let slot = &mut found.entry(index).or_default()[k];
                // Two files for one map (say .png and .exr): keep the preferred extension.
                if slot.as_ref().is_none_or(|old| extension_rank(old) > extension_rank(&path)) {
                    *slot = Some(path);
                }
            }
        }
        if found.is_empty() {
            bail!(
                "MatFusion dataset {} has no maps named like diffuse/0000001_diffuse.png",
                root.display()
            );
        }
        Ok(Self { root: root.to_path_buf(), materials: found.into_iter().collect() })
    }

    /// The path a map of material `index` is expected at (PNG).
    fn expected_path(&self, index: u64, map: Map) -> PathBuf {
        self.root.join(map.name()).join(format!("{index:07}_{}.png", map.name()))
    }
}

impl SvbrdfSource for MatfusionDataset {
    fn len(&self) -> usize {
        self.materials.len()
    }
    fn name(&self, i: usize) -> String {
        format!("{:07}", self.materials[i].0)
    }
    fn load(&self, i: usize) -> Result<Svbrdf> {
        let (index, files) = self.materials.get(i).ok_or_else(|| out_of_range(i, self.len(), &self.root))?;
        let f = |k: usize| files[k].as_deref();
        load_maps([f(0), f(1), f(2), f(3)], |m| self.expected_path(*index, m))
    }
}

fn out_of_range(i: usize, len: usize, root: &Path) -> anyhow::Error {
    anyhow!("material {i} requested from {}, which has {len}", root.display())
}

// ------------------------------------------------------- per-material dirs

/// Per-material folders: `ROOT/NAME/diffuse.png`, `specular.png`,
/// `roughness.png`, `normals.png` (`normal.*`, `.exr`, `.jpg` accepted).
/// A folder that itself holds the maps is a one-material dataset.
/// Materials are the sub-folders holding at least one map, sorted by name.
pub struct MaterialDirsDataset {
    root: PathBuf,
    dirs: Vec<PathBuf>,
}

/// The file of `map` in a material folder, if any.
fn find_map_file(dir: &Path, map: Map) -> Option<PathBuf> {
    let stems: &[&str] = if map == Map::Normals { &["normals", "normal"] } else { &[map.name()] };
    stems
        .iter()
        .flat_map(|stem| MAP_EXTENSIONS.iter().map(move |ext| dir.join(format!("{stem}.{ext}"))))
        .find(|p| p.is_file())
}

fn is_material_dir(dir: &Path) -> bool {
    Map::ALL.into_iter().any(|m| find_map_file(dir, m).is_some())
}

impl MaterialDirsDataset {
    pub fn open(root: &Path) -> Result<Self> {
        if !root.is_dir() {
            bail!("material folder dataset {} is not a folder", root.display());
        }
        let dirs = if find_map_file(root, Map::Diffuse).is_some() {
            vec![root.to_path_buf()]
        } else {
            io::sorted_entries(root)?.into_iter().filter(|p| p.is_dir() && is_material_dir(p)).collect()
        };
        if dirs.is_empty() {
            bail!(
                "{} has no material folders (NAME/diffuse.png, specular.png, roughness.png, normals.png)",
                root.display()
            );
        }
        Ok(Self { root: root.to_path_buf(), dirs })
    }
}

impl SvbrdfSource for MaterialDirsDataset {
    fn len(&self) -> usize {
        self.dirs.len()
    }
    fn name(&self, i: usize) -> String {
        let d = &self.dirs[i];
        d.file_name().map_or_else(|| d.display().to_string(), |n| n.to_string_lossy().into_owned())
    }
    fn load(&self, i: usize) -> Result<Svbrdf> {
        let dir = self.dirs.get(i).ok_or_else(|| out_of_range(i, self.len(), &self.root))?;
        let files = Map::ALL.map(|m| find_map_file(dir, m));
        let f = |k: usize| files[k].as_deref();
        load_maps([f(0), f(1), f(2), f(3)], |m| dir.join(format!("{}.png", m.name())))
    }
}

// ------------------------------------------------------------------ strips

/// INRIA strip images: each file is square H x H panels side by side,
/// `normal | diffuse | roughness | specular` (4H wide) or
/// `render | normal | diffuse | roughness | specular` (5H wide). Opened from
/// one file or a folder of `.png`/`.jpg` files (sorted by name); every
/// file's size is checked when opening.
pub struct StripDataset {
    root: PathBuf,
    files: Vec<PathBuf>,
}

/// Number of panels of a `width x height` strip, or an error naming `path`.
fn strip_panels(path: &Path, width: usize, height: usize) -> Result<usize> {
    match (height > 0).then(|| width / height.max(1)) {
        Some(n @ (4 | 5)) if width == n * height => Ok(n),
        _ => bail!(
            "strip {} is {width}x{height}; expected 4 or 5 square panels side by side (width 4H or 5H)",
            path.display()
        ),
    }
}

fn is_strip_file(path: &Path) -> bool {
    path.is_file()
        && path
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| matches!(e.to_ascii_lowercase().as_str(), "png" | "jpg" | "jpeg"))
}

/// Reads one strip: the material and, for a 5-panel strip, the rendered
/// photo (`[3, H, W]`, linearised with ^2.2 like the diffuse map).
pub fn read_strip(path: &Path) -> Result<(Svbrdf, Option<Image>)> {
    let (image, format) = io::read_image_with_format(path)?;
    let panels = strip_panels(path, image.width, image.height)?;
    let h = image.height;
    let panel = |k: usize| image.columns(k * h, h);
    let first = panels - 4;
    // The render is radiance, not an albedo: no range to check.
    let linearise = |im: Image| if format.is_float() { io::to_rgb(&im) } else { io::to_rgb(&im).map(gamma_decode) };
    let render = if panels == 5 { Some(linearise(panel(0)?)) } else { None };
    let s = Svbrdf {
        normal: decode_map(Map::Normals, panel(first)?, format, path)?,
        diffuse: decode_map(Map::Diffuse, panel(first + 1)?, format, path)?,
        roughness: decode_map(Map::Roughness, panel(first + 2)?, format, path)?,
        specular: decode_map(Map::Specular, panel(first + 3)?, format, path)?,
        height_field: None,
    };
    s.validate().map_err(|e| anyhow!("strip {}: {e}", path.display()))?;
    Ok((s, render))
}

impl StripDataset {
    /// `root_or_file`: one strip image, or a folder of them.
    pub fn open(root_or_file: &Path) -> Result<Self> {
        let files = if root_or_file.is_file() {
            vec![root_or_file.to_path_buf()]
        } else if root_or_file.is_dir() {
            io::sorted_entries(root_or_file)?.into_iter().filter(|p| is_strip_file(p)).collect()
        } else {
            bail!("strip dataset {} does not exist", root_or_file.display());
        };
        if files.is_empty() {
            bail!("{} has no strip images (*.png, *.jpg)", root_or_file.display());
        }
        for f in &files {
            let (w, h) = image::ImageReader::open(f)
                .and_then(|r| r.with_guessed_format())
                .map_err(|e| e.to_string())
                .and_then(|r| r.into_dimensions().map_err(|e| e.to_string()))
                .map_err(|e| anyhow!("cannot read image {}: {e}", f.display()))?;
            strip_panels(f, w as usize, h as usize)?;
        }
        Ok(Self { root: root_or_file.to_path_buf(), files })
    }

    /// Material `i` and its rendered photo when the strip has 5 panels.
    pub fn load_with_render(&self, i: usize) -> Result<(Svbrdf, Option<Image>)> {
        read_strip(self.files.get(i).ok_or_else(|| out_of_range(i, self.len(), &self.root))?)
    }
}

impl SvbrdfSource for StripDataset {
    fn len(&self) -> usize {
        self.files.len()
    }
    fn name(&self, i: usize) -> String {
        let f = &self.files[i];
        f.file_stem().map_or_else(|| f.display().to_string(), |n| n.to_string_lossy().into_owned())
    }
    fn load(&self, i: usize) -> Result<Svbrdf> {
        Ok(self.load_with_render(i)?.0)
    }
}

// ----------------------------------------------------------- autodetection

/// Opens whichever layout `path` holds, checked in this order:
/// an image file (one strip); a folder with a `diffuse/` sub-folder
/// (MatFusion); a folder holding `diffuse.png` or sub-folders holding maps
/// (per-material folders); a folder of `.png`/`.jpg` files (strips).
pub fn open_dataset(path: &Path) -> Result<Box<dyn SvbrdfSource>> {
    if path.is_file() {
        return Ok(Box::new(StripDataset::open(path)?));
    }
    if !path.is_dir() {
        bail!("dataset {} does not exist", path.display());
    }
    if path.join(Map::Diffuse.name()).is_dir() {
        return Ok(Box::new(MatfusionDataset::open(path)?));
    }
    let entries = io::sorted_entries(path)?;
    if is_material_dir(path) || entries.iter().any(|p| p.is_dir() && is_material_dir(p)) {
        return Ok(Box::new(MaterialDirsDataset::open(path)?));
    }
    if entries.iter().any(|p| is_strip_file(p)) {
        return Ok(Box::new(StripDataset::open(path)?));
    }
    bail!(
        "no SVBRDF dataset found in {}; looked for: a MatFusion layout (diffuse/, specular/, roughness/, \
         normals/ holding 0000001_diffuse.png ...), material folders (NAME/diffuse.png, specular.png, \
         roughness.png, normals.png), and strip images (*.png of 4 or 5 square panels)",
        path.display()
    )
}

// ------------------------------------------------- unreadable materials

/// A material of a dataset that could not be read, and why (one line).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Unreadable {
    pub name: String,
    pub reason: String,
}

/// The first `n` materials of `ds` with their names, each passed through
/// `prepare`, going on past those that cannot be read or prepared: one
/// published map with a bad pixel should not stop a whole evaluation.
/// Each one skipped is named in a `warning: skipped material` line once
/// the others are read; callers report them and end with
/// [`unreadable_error`]. When none can be read, the error names the first.
pub fn load_readable(ds: &dyn SvbrdfSource, n: usize, prepare: impl Fn(Svbrdf) -> Result<Svbrdf>) -> Result<(Vec<(String, Svbrdf)>, Vec<Unreadable>)> {
    let (mut read, mut unreadable) = (Vec::new(), Vec::new());
    for i in 0..n.min(ds.len()) {
        let name = ds.name(i);
        match ds.load(i).and_then(&prepare) {
            Ok(m) => read.push((name, m)),
            Err(e) => unreadable.push(Unreadable { name, reason: format!("{e:#}").replace('\n', " ") }),
        }
    }
    if read.is_empty() {
        match unreadable.as_slice() {
            [] => bail!("the dataset holds no materials"),
            [one] => bail!("material {}: {}", one.name, one.reason),
            [first, ..] => bail!("none of the {} materials could be read; the first, {}: {}", unreadable.len(), first.name, first.reason),
        }
    }
    for u in &unreadable {
        eprintln!("warning: skipped material {}: {}", u.name, u.reason);
    }
    Ok((read, unreadable))
}

/// The error a command ends with when it skipped `unreadable` of `total`
/// materials, its outputs written for the others (exit code 1).
pub fn unreadable_error(unreadable: &[Unreadable], total: usize) -> anyhow::Error {
    let names: Vec<&str> = unreadable.iter().map(|u| u.name.as_str()).collect();
    anyhow!("{} of {total} materials could not be read and were skipped: {}", unreadable.len(), names.join(", "))
}

// ----------------------------------------------------------------- writers

/// The four maps as stored in 8-bit files: diffuse and specular
/// gamma-encoded (^(1/2.2)), roughness as is, normals as (n + 1) / 2.
/// `[3|3|1|3, H, W]`, all in [0, 1].
fn encoded_maps(s: &Svbrdf) -> [Image; 4] {
    [
        s.diffuse.map(gamma_encode),
        s.specular.map(gamma_encode),
        s.roughness.map(|v| v.clamp(0.0, 1.0)),
        encode_normal_map(&s.normal),
    ]
}

fn create_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| anyhow!("cannot create folder {}: {e}", dir.display()))
}

fn check_material(s: &Svbrdf, target: &Path) -> Result<()> {
    s.validate().map_err(|e| anyhow!("cannot write material {}: {e}", target.display()))
}

/// Writes material number `index` (1-based) in the MatFusion layout under
/// `root` as 8-bit PNGs, creating the four folders as needed. Each file is
/// written atomically.
pub fn write_matfusion(root: &Path, index: usize, s: &Svbrdf) -> Result<()> {
    if index == 0 {
        bail!("MatFusion material indices are 1-based; cannot write index 0 under {}", root.display());
    }
    check_material(s, root)?;
    for (map, image) in Map::ALL.into_iter().zip(encoded_maps(s)) {
        let dir = root.join(map.name());
        create_dir(&dir)?;
        io::write_png(&dir.join(format!("{index:07}_{}.png", map.name())), &image, BitDepth::Eight)?;
    }
    Ok(())
}

/// Writes a material folder `dir/{diffuse,specular,roughness,normals}.png`
/// (8-bit, encoded as in [`write_matfusion`]), creating `dir` as needed.
pub fn write_material_dir(dir: &Path, s: &Svbrdf) -> Result<()> {
    check_material(s, dir)?;
    create_dir(dir)?;
    for (map, image) in Map::ALL.into_iter().zip(encoded_maps(s)) {
        io::write_png(&dir.join(format!("{}.png", map.name())), &image, BitDepth::Eight)?;
    }
    Ok(())
}

/// Writes an 8-bit strip PNG: `[render |] normal | diffuse | roughness |
/// specular`, each panel H x H. The material must be square; `render` is a
/// linear `[3, H, W]` image, stored gamma-encoded (clamped to [0, 1]) like
/// the diffuse map, so [`read_strip`] gives it back linear.
pub fn write_strip(path: &Path, s: &Svbrdf, render: Option<&Image>) -> Result<()> {
    check_material(s, path)?;
    let (h, w) = (s.height(), s.width());
    if h != w {
        bail!("cannot write strip {}: strip panels are square but the material is {w}x{h}", path.display());
    }
    if let Some(r) = render {
        if (r.channels, r.height, r.width) != (3, h, w) {
            bail!(
                "cannot write strip {}: the render is {}x{} with {} channels, expected {w}x{h} RGB",
                path.display(),
                r.width,
                r.height,
                r.channels
            );
        }
    }
    let [diffuse, specular, roughness, normals] = encoded_maps(s);
    let roughness = io::to_rgb(&roughness);
    let mut panels: Vec<Image> = render.map(|r| r.map(gamma_encode)).into_iter().collect();
    panels.extend([normals, diffuse, roughness, specular]);
    let strip = Image::from_fn(3, h, panels.len() * h, |c, y, x| panels[x / h].get(c, y, x % h));
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        create_dir(parent)?;
    }
    io::write_png(path, &strip, BitDepth::Eight)
}

// ------------------------------------------------------------------- crops

fn check_crop(s: &Svbrdf, size: usize) -> Result<()> {
    if size == 0 || s.height() < size || s.width() < size {
        bail!("cannot crop {size}x{size} from a {}x{} material", s.width(), s.height());
    }
    Ok(())
}

/// A `size x size` crop at a uniformly random position (every valid
/// offset equally likely). Errors if the material is smaller than `size`.
pub fn random_crop<R: rand::Rng + ?Sized>(s: &Svbrdf, size: usize, rng: &mut R) -> Result<Svbrdf> {
    check_crop(s, size)?;
    let top = rng.random_range(0..=s.height() - size);
    let left = rng.random_range(0..=s.width() - size);
    s.crop(top, left, size, size)
}

/// The central `size x size` crop (offsets rounded down). Errors if the
/// material is smaller than `size`.
pub fn center_crop(s: &Svbrdf, size: usize) -> Result<Svbrdf> {
    check_crop(s, size)?;
    s.crop((s.height() - size) / 2, (s.width() - size) / 2, size, size)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::svbrdf::decode_normal;
    use rand::SeedableRng;

    fn message(e: anyhow::Error) -> String {
        let m = format!("{e:#}");
        assert!(!m.contains('\n'), "multi-line error: {m}");
        m
    }

    /// Writes an 8-bit PNG from a per-pixel closure with the image crate,
    /// independent of our writer.
    fn save_rgb(path: &Path, w: u32, h: u32, f: impl Fn(u32, u32) -> [u8; 3]) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        image::RgbImage::from_fn(w, h, |x, y| image::Rgb(f(x, y))).save(path).unwrap();
    }

    fn save_gray(path: &Path, w: u32, h: u32, v: u8) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        image::GrayImage::from_pixel(w, h, image::Luma([v])).save(path).unwrap();
    }

    fn lin(code: u8) -> f32 {
        (code as f32 / 255.0).powf(2.2)
    }

    fn close(a: f32, b: f32, tol: f32) -> bool {
        (a - b).abs() <= tol
    }

    /// A spatially varying 16x16 material with values across the ranges.
    fn varied(n: usize) -> Svbrdf {
        let nrm = |y: usize, x: usize| {
            let (a, b) = (x as f32 / n as f32 - 0.5, 0.3 - y as f32 / n as f32);
            let l = (a * a + b * b + 1.0).sqrt();
            [a / l, b / l, 1.0 / l]
        };
        Svbrdf {
            diffuse: Image::from_fn(3, n, n, |c, _, x| (0.05 + 0.3 * c as f32) * (x + 1) as f32 / n as f32),
            specular: Image::from_fn(3, n, n, |c, y, _| 0.02 + 0.05 * c as f32 + 0.5 * y as f32 / n as f32),
            roughness: Image::from_fn(1, n, n, |_, y, x| 0.05 + 0.9 * ((x + y) % n) as f32 / n as f32),
            normal: Image::from_fn(3, n, n, |c, y, x| nrm(y, x)[c]),
            height_field: None,
        }
    }

    fn max_abs_diff(a: &Image, b: &Image) -> f32 {
        assert_eq!((a.channels, a.height, a.width), (b.channels, b.height, b.width));
        a.data.iter().zip(&b.data).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
    }

    /// 8-bit quantisation bounds: gamma-encoded maps lose at most
    /// 2.2 * 0.5/255 in linear terms, roughness 0.5/255, normals about
    /// 2 * 0.5/255 per component before renormalisation.
    fn assert_quantised_equal(a: &Svbrdf, b: &Svbrdf) {
        assert!(max_abs_diff(&a.diffuse, &b.diffuse) < 2.2 * 0.5 / 255.0 + 1e-5);
        assert!(max_abs_diff(&a.specular, &b.specular) < 2.2 * 0.5 / 255.0 + 1e-5);
        assert!(max_abs_diff(&a.roughness, &b.roughness) < 0.5 / 255.0 + 1e-6);
        assert!(max_abs_diff(&a.normal, &b.normal) < 2.0 / 255.0);
    }

    #[test]
    fn matfusion_fixture_is_linearised_and_decoded() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        // Materials 1 and 3 (a gap), written with the image crate directly.
        for (index, d) in [(1u32, 128u8), (3, 64)] {
            let id = format!("{index:07}");
            save_rgb(&root.join(format!("diffuse/{id}_diffuse.png")), 16, 16, |x, _| [d, x as u8 * 10, 255]);
            save_rgb(&root.join(format!("specular/{id}_specular.png")), 16, 16, |_, y| [10, 20, y as u8]);
            save_rgb(&root.join(format!("normals/{id}_normals.png")), 16, 16, |x, _| {
                if x < 8 { [128, 128, 255] } else { [200, 100, 220] }
            });
            if index == 1 {
                save_gray(&root.join(format!("roughness/{id}_roughness.png")), 16, 16, 51);
            } else {
                // RGB roughness: the first channel counts.
                save_rgb(&root.join(format!("roughness/{id}_roughness.png")), 16, 16, |_, _| [102, 0, 255]);
            }
        }
        // Unrelated files are ignored: a temp file, another map's name, text.
        std::fs::write(root.join("diffuse/.0000002_diffuse.png.tmp-1-0"), b"x").unwrap();
        std::fs::write(root.join("diffuse/notes.txt"), b"x").unwrap();
        std::fs::write(root.join("diffuse/0000009_specular.png"), b"x").unwrap();

        let ds = open_dataset(root).unwrap();
        assert_eq!(ds.len(), 2);
        assert_eq!((ds.name(0), ds.name(1)), ("0000001".to_string(), "0000003".to_string()));
        let s = ds.load(0).unwrap();
        assert_eq!((s.height(), s.width()), (16, 16));
        assert_eq!(s.diffuse.get(0, 5, 5), (128f32 / 255.0).powf(2.2));
        assert!(close(s.diffuse.get(1, 0, 7), lin(70), 1e-7));
        assert_eq!(s.diffuse.get(2, 9, 9), 1.0);
        assert!(close(s.specular.get(2, 4, 0), lin(4), 1e-7));
        assert!(close(s.specular.get(0, 4, 0), lin(10), 1e-7));
        assert!(close(s.roughness.get(0, 3, 3), 0.2, 1e-7));
        let n0 = decode_normal([128.0 / 255.0, 128.0 / 255.0, 1.0]);
        let n1 = decode_normal([200.0 / 255.0, 100.0 / 255.0, 220.0 / 255.0]);
        for c in 0..3 {
            assert!(close(s.normal.get(c, 2, 3), n0[c], 1e-6));
            assert!(close(s.normal.get(c, 2, 12), n1[c], 1e-6));
        }
        assert!(s.normal.get(0, 2, 12) > 0.3 && s.normal.get(1, 2, 12) < -0.1);
        let s3 = ds.load(1).unwrap();
        assert!(close(s3.diffuse.get(0, 0, 0), lin(64), 1e-7));
        assert!(close(s3.roughness.get(0, 0, 0), 0.4, 1e-7));
        assert!(message(ds.load(2).unwrap_err()).contains("has 2"));
    }

    #[test]
    fn matfusion_writer_round_trip_and_exr_maps() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("set");
        let a = varied(16);
        let b = Svbrdf::uniform(16, 16, [0.3, 0.2, 0.1], [0.04; 3], 0.7);
        write_matfusion(&root, 2, &b).unwrap();
        write_matfusion(&root, 1, &a).unwrap();
        assert!(root.join("normals/0000001_normals.png").is_file());
        assert!(message(write_matfusion(&root, 0, &a).unwrap_err()).contains("1-based"));
        let ds = MatfusionDataset::open(&root).unwrap();
        assert_eq!(ds.len(), 2);
        assert_quantised_equal(&ds.load(0).unwrap(), &a);
        assert_quantised_equal(&ds.load(1).unwrap(), &b);
        // An EXR diffuse map is linear already: preferred after PNG, so
        // replace material 2's PNG with it.
        std::fs::remove_file(root.join("diffuse/0000002_diffuse.png")).unwrap();
        let linear = Image::from_fn(3, 16, 16, |c, _, _| [0.25, 0.95, 0.0][c]);
        io::write_exr(&root.join("diffuse/0000002_diffuse.exr"), &linear).unwrap();
        let s = MatfusionDataset::open(&root).unwrap().load(1).unwrap();
        assert_eq!(s.diffuse, linear);
        // An albedo above 1 is no albedo (float files can hold anything).
        io::write_exr(&root.join("diffuse/0000002_diffuse.exr"), &Image::from_fn(3, 16, 16, |c, _, _| [0.25, 1.5, 0.0][c])).unwrap();
        let m = message(MatfusionDataset::open(&root).unwrap().load(1).unwrap_err());
        assert!(m.contains("0000002_diffuse.exr has the value 1.5 at row 0, column 0, channel 1"), "{m}");
    }

    /// Maps that decode but describe no material: refused with one line
    /// naming the file (albedos outside [0, 1], zero-length normals);
    /// roughness under the floor is raised to it; rounding slack clamps.
    #[test]
    fn absurd_map_values_are_refused_or_clamped() {
        let dir = tempfile::tempdir().unwrap();
        let m = dir.path().join("m");
        write_material_dir(&m, &Svbrdf::uniform(8, 8, [0.3; 3], [0.04; 3], 0.5)).unwrap();
        let load = || open_dataset(&m).unwrap().load(0);
        let exr = |name: &str, c: usize, v: f32| {
            for ext in ["png", "exr"] {
                let _ = std::fs::remove_file(m.join(format!("{name}.{ext}")));
            }
            io::write_exr(&m.join(format!("{name}.exr")), &Image::filled(c, 8, 8, v)).unwrap();
        };
        exr("diffuse", 3, -1.0);
        let e = message(load().unwrap_err());
        assert!(e.contains("diffuse map") && e.contains("diffuse.exr has the value -1") && e.contains("[0, 1]"), "{e}");
        exr("diffuse", 3, 1.005); // rounding: clamped
        assert_eq!(load().unwrap().diffuse, Image::filled(3, 8, 8, 1.0));
        exr("specular", 3, 1e30);
        assert!(message(load().unwrap_err()).contains("specular.exr has the value 1000000000000000000000000000000"));
        exr("specular", 3, 0.04);
        exr("roughness", 1, 0.0);
        assert_eq!(load().unwrap().roughness, Image::filled(1, 8, 8, crate::data::procedural::MIN_ROUGHNESS));
        exr("roughness", 1, 7.0);
        assert!(message(load().unwrap_err()).contains("roughness.exr has the value 7"));
        exr("roughness", 1, 0.5);
        exr("normals", 3, 0.5);
        let e = message(load().unwrap_err());
        assert!(e.contains("normals.exr holds a zero-length normal at row 0, column 0"), "{e}");
        // Short but not zero: normalised.
        io::write_exr(&m.join("normals.exr"), &Image::from_fn(3, 8, 8, |c, _, _| [0.5, 0.5, 0.52][c])).unwrap();
        assert!(max_abs_diff(&load().unwrap().normal, &Image::from_fn(3, 8, 8, |c, _, _| [0.0, 0.0, 1.0][c])) < 1e-6);
        // NaN: refused with the place (by the reader; decode_map too, for
        // maps from elsewhere, and check_range, which NaN once slipped past).
        exr::prelude::write_rgb_file(m.join("normals.exr"), 8, 8, |x, y| (0.5f32, if (x, y) == (4, 1) { f32::NAN } else { 0.5 }, 1.0f32)).unwrap();
        let e = message(load().unwrap_err());
        assert!(e.contains("normals.exr") && e.contains("NaN/Inf") && e.contains("row 1, column 4"), "{e}");
        let mut nan = Image::filled(3, 8, 8, 0.5);
        nan.set(1, 1, 4, f32::NAN);
        let e = message(decode_map(Map::Normals, nan.clone(), FileFormat::Exr, Path::new("n.exr")).unwrap_err());
        assert!(e.contains("n.exr holds a NaN/Inf value at row 1, column 4"), "{e}");
        let e = message(decode_map(Map::Diffuse, nan, FileFormat::Exr, Path::new("d.exr")).unwrap_err());
        assert!(e.contains("d.exr has the value NaN at row 1, column 4, channel 1"), "{e}");
        // An 8-bit grey pixel is the zero vector as the file stores it
        // (length sqrt(3) / 255): refused.
        std::fs::remove_file(m.join("normals.exr")).unwrap();
        save_rgb(&m.join("normals.png"), 8, 8, |x, y| if (x, y) == (3, 2) { [128, 128, 128] } else { [128, 128, 255] });
        assert!(message(load().unwrap_err()).contains("normals.png holds a zero-length normal at row 2, column 3"));
        // The pixel: codes (130, 139, 131) decode to (5, 23, 7) / 255,
        // length 0.096; normalised to (5, 23, 7) / sqrt(603).
        save_rgb(&m.join("normals.png"), 8, 8, |x, y| if (x, y) == (3, 2) { [130, 139, 131] } else { [128, 128, 255] });
        let normal = load().unwrap().normal;
        let want = [5.0, 23.0, 7.0].map(|v: f32| v / 603f32.sqrt());
        // (2 x code - 1 cancels: each component is off by up to 1e-7 before
        // the division by the length.)
        for c in 0..3 {
            assert!(close(normal.get(c, 2, 3), want[c], 1e-5), "{c}: {}", normal.get(c, 2, 3));
        }
        // One code step from grey, (129, 128, 128): length sqrt(11) / 255, kept.
        save_rgb(&m.join("normals.png"), 8, 8, |x, y| if (x, y) == (3, 2) { [129, 128, 128] } else { [128, 128, 255] });
        let n = load().unwrap().normal;
        let len = (0..3).map(|c| n.get(c, 2, 3).powi(2)).sum::<f32>().sqrt();
        assert!(close(len, 1.0, 1e-6) && close(n.get(0, 2, 3), 3.0 / 11f32.sqrt(), 1e-4), "{len} {}", n.get(0, 2, 3));
    }

    /// An INRIA strip whose normal panel holds one short normal (the
    /// issue's pixel) loads, that normal unit length and pointing as stored.
    #[test]
    fn strip_with_a_short_normal_is_normalised() {
        let dir = tempfile::tempdir().unwrap();
        let h = 16u32;
        // normal | diffuse | roughness | specular
        save_rgb(&dir.path().join("tile.png"), 4 * h, h, |x, y| match (x / h, x % h, y) {
            (0, 5, 3) => [130, 139, 131],
            (0, ..) => [128, 128, 255],
            (1, ..) => [180, 120, 60],
            (2, ..) => [100, 100, 100],
            _ => [40, 40, 40],
        });
        let s = open_dataset(dir.path()).unwrap().load(0).unwrap();
        let n = [0, 1, 2].map(|c| s.normal.get(c, 3, 5));
        assert!(close((n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt(), 1.0, 1e-6), "{n:?}");
        let want = [5.0, 23.0, 7.0].map(|v: f32| v / 603f32.sqrt());
        for c in 0..3 {
            assert!(close(n[c], want[c], 1e-5), "{n:?} vs {want:?}");
            assert!(close(s.normal.get(c, 3, 6), decode_normal([128.0 / 255.0, 128.0 / 255.0, 1.0])[c], 1e-6));
        }
    }

    /// Going on past unreadable materials: the others with their names,
    /// the bad ones with theirs and the reason; none readable is an error
    /// naming the first.
    #[test]
    fn unreadable_materials_are_skipped_and_named() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        for name in ["a", "b", "c"] {
            write_material_dir(&root.join(name), &varied(16)).unwrap();
        }
        std::fs::write(root.join("b/diffuse.png"), b"not a png").unwrap();
        let ds = open_dataset(root).unwrap();
        let (read, skipped) = load_readable(ds.as_ref(), 10, Ok).unwrap();
        assert_eq!(read.iter().map(|(n, _)| n.as_str()).collect::<Vec<_>>(), ["a", "c"]);
        assert_eq!(skipped.len(), 1);
        assert!(skipped[0].name == "b" && skipped[0].reason.contains("b/diffuse.png"), "{skipped:?}");
        assert_eq!(message(unreadable_error(&skipped, 3)), "1 of 3 materials could not be read and were skipped: b");
        // `prepare` failing counts as unreadable too; only the first n are read.
        let e = message(load_readable(ds.as_ref(), 1, |m| center_crop(&m, 32)).unwrap_err());
        assert!(e.starts_with("material a: cannot crop 32x32"), "{e}");
        std::fs::write(root.join("a/diffuse.png"), b"x").unwrap();
        std::fs::write(root.join("c/diffuse.png"), b"x").unwrap();
        let e = message(load_readable(ds.as_ref(), 10, Ok).unwrap_err());
        assert!(e.starts_with("none of the 3 materials could be read; the first, a: ") && e.contains("a/diffuse.png"), "{e}");
        let e = message(ds.load_named(2).unwrap_err());
        assert!(e.starts_with("material c: ") && e.contains("c/diffuse.png"), "{e}");
    }

    #[test]
    fn material_dirs_layout() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        let a = varied(16);
        write_material_dir(&root.join("wood"), &a).unwrap();
        // A hand-written material with the "normal.png" spelling.
        let m = root.join("metal");
        save_rgb(&m.join("diffuse.png"), 16, 16, |_, _| [128, 128, 128]);
        save_rgb(&m.join("specular.png"), 16, 16, |_, _| [255, 200, 100]);
        save_gray(&m.join("roughness.png"), 16, 16, 255);
        save_rgb(&m.join("normal.png"), 16, 16, |_, _| [128, 128, 255]);
        std::fs::create_dir(root.join("not_a_material")).unwrap();
        std::fs::write(root.join("README.txt"), b"x").unwrap();

        let ds = open_dataset(root).unwrap();
        assert_eq!(ds.len(), 2);
        assert_eq!((ds.name(0), ds.name(1)), ("metal".to_string(), "wood".to_string()));
        let metal = ds.load(0).unwrap();
        assert_eq!(metal.diffuse.get(1, 4, 4), (128f32 / 255.0).powf(2.2));
        assert!(close(metal.specular.get(2, 0, 0), lin(100), 1e-7));
        assert_eq!(metal.roughness.get(0, 15, 15), 1.0);
        assert!(close(metal.normal.get(2, 1, 1), 1.0, 1e-4));
        assert_quantised_equal(&ds.load(1).unwrap(), &a);

        // One material folder on its own.
        let one = open_dataset(&root.join("wood")).unwrap();
        assert_eq!((one.len(), one.name(0)), (1, "wood".to_string()));
        assert_quantised_equal(&one.load(0).unwrap(), &a);
    }

    #[test]
    fn strips_both_variants_in_panel_order() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        let h = 16u32;
        // Each panel a distinct constant, hand-written.
        let panel_values: [[u8; 3]; 5] = [[30, 60, 90], [100, 150, 250], [128, 64, 32], [77, 77, 77], [10, 20, 40]];
        save_rgb(&root.join("b_five.png"), 5 * h, h, |x, _| panel_values[(x / h) as usize]);
        save_rgb(&root.join("a_four.png"), 4 * h, h, |x, _| panel_values[(x / h) as usize + 1]);
        let ds = open_dataset(root).unwrap();
        assert_eq!((ds.len(), ds.name(0), ds.name(1)), (2, "a_four".to_string(), "b_five".to_string()));
        let check = |s: &Svbrdf| {
            assert_eq!((s.height(), s.width()), (16, 16));
            let n = decode_normal([100.0 / 255.0, 150.0 / 255.0, 250.0 / 255.0]);
            for c in 0..3 {
                assert!(close(s.normal.get(c, 3, 15), n[c], 1e-6));
                assert!(close(s.diffuse.get(c, 3, 0), lin([128, 64, 32][c]), 1e-7));
                assert!(close(s.specular.get(c, 15, 15), lin([10, 20, 40][c]), 1e-7));
            }
            assert!(close(s.roughness.get(0, 7, 7), 77.0 / 255.0, 1e-7));
        };
        check(&ds.load(0).unwrap());
        check(&ds.load(1).unwrap());
        let strips = StripDataset::open(root).unwrap();
        let (_, render) = strips.load_with_render(1).unwrap();
        let render = render.unwrap();
        assert!(close(render.get(0, 0, 0), lin(30), 1e-7) && close(render.get(2, 15, 15), lin(90), 1e-7));
        assert!(strips.load_with_render(0).unwrap().1.is_none());

        // Writer round trip, with and without a render; a single file opens too.
        let a = varied(16);
        let photo = Image::from_fn(3, 16, 16, |c, y, x| 0.1 * c as f32 + 0.02 * (x + y) as f32);
        let p = root.join("out/five.png");
        write_strip(&p, &a, Some(&photo)).unwrap();
        let (s, r) = read_strip(&p).unwrap();
        assert_quantised_equal(&s, &a);
        assert!(max_abs_diff(&r.unwrap(), &photo) < 2.2 * 0.5 / 255.0 + 1e-5);
        let p4 = root.join("out/four.png");
        write_strip(&p4, &a, None).unwrap();
        let one = open_dataset(&p4).unwrap();
        assert_eq!((one.len(), one.name(0)), (1, "four".to_string()));
        assert_quantised_equal(&one.load(0).unwrap(), &a);
        let rect = Svbrdf::uniform(8, 16, [0.1; 3], [0.1; 3], 0.5);
        assert!(message(write_strip(&p4, &rect, None).unwrap_err()).contains("square"));
        assert!(message(write_strip(&p4, &a, Some(&Image::new(3, 8, 8))).unwrap_err()).contains("render"));
    }

    #[test]
    fn bad_strips_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("wide.png");
        save_rgb(&p, 60, 16, |_, _| [0, 0, 0]);
        let m = message(open_dataset(&p).map(|_| ()).unwrap_err());
        assert!(m.contains("wide.png") && m.contains("60x16"), "{m}");
        let m = message(read_strip(&p).unwrap_err());
        assert!(m.contains("wide.png") && m.contains("4H or 5H"), "{m}");
        let m = message(open_dataset(dir.path()).map(|_| ()).unwrap_err());
        assert!(m.contains("wide.png"), "{m}");
        // Right size header but corrupt data: error on load, naming the file.
        let good = dir.path().join("ok/s.png");
        save_rgb(&good, 64, 16, |x, y| [x as u8, y as u8, 7]);
        let bytes = std::fs::read(&good).unwrap();
        std::fs::write(&good, &bytes[..bytes.len() / 2]).unwrap();
        let ds = open_dataset(&dir.path().join("ok")).unwrap();
        let m = message(ds.load(0).unwrap_err());
        assert!(m.contains("ok/s.png"), "{m}");
    }

    #[test]
    fn missing_and_inconsistent_components_are_named() {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("mf");
        write_matfusion(&root, 1, &varied(16)).unwrap();
        write_matfusion(&root, 2, &varied(16)).unwrap();
        std::fs::remove_file(root.join("specular/0000002_specular.png")).unwrap();
        let ds = open_dataset(&root).unwrap();
        assert_eq!(ds.len(), 2);
        let m = message(ds.load(1).unwrap_err());
        assert!(m.contains("specular/0000002_specular.png") && m.contains("missing"), "{m}");
        // Size mismatch names the offending file.
        save_gray(&root.join("roughness/0000001_roughness.png"), 8, 8, 10);
        let m = message(ds.load(0).unwrap_err());
        assert!(m.contains("roughness/0000001_roughness.png") && m.contains("8x8") && m.contains("16x16"), "{m}");
        // Garbage in place of a map.
        std::fs::write(root.join("normals/0000001_normals.png"), b"garbage garbage").unwrap();
        save_gray(&root.join("roughness/0000001_roughness.png"), 16, 16, 10);
        let m = message(ds.load(0).unwrap_err());
        assert!(m.contains("normals/0000001_normals.png"), "{m}");
        // A missing map folder is caught when opening.
        std::fs::remove_dir_all(root.join("roughness")).unwrap();
        let m = message(open_dataset(&root).map(|_| ()).unwrap_err());
        assert!(m.contains("roughness/"), "{m}");

        let mats = dir.path().join("mats");
        write_material_dir(&mats.join("x"), &varied(16)).unwrap();
        std::fs::remove_file(mats.join("x/normals.png")).unwrap();
        let m = message(open_dataset(&mats).unwrap().load(0).unwrap_err());
        assert!(m.contains("x/normals.png"), "{m}");
        // A gray normal map cannot be decoded.
        save_gray(&mats.join("x/normals.png"), 16, 16, 128);
        let m = message(open_dataset(&mats).unwrap().load(0).unwrap_err());
        assert!(m.contains("x/normals.png") && m.contains("channel"), "{m}");
    }

    #[test]
    fn open_dataset_explains_what_it_looked_for() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("notes.txt"), b"x").unwrap();
        let m = message(open_dataset(dir.path()).map(|_| ()).unwrap_err());
        assert!(m.contains("MatFusion") && m.contains("normals.png") && m.contains("strip"), "{m}");
        let m = message(open_dataset(&dir.path().join("nope")).map(|_| ()).unwrap_err());
        assert!(m.contains("nope") && m.contains("does not exist"), "{m}");
        std::fs::create_dir(dir.path().join("diffuse")).unwrap();
        for sub in ["specular", "roughness", "normals"] {
            std::fs::create_dir(dir.path().join(sub)).unwrap();
        }
        let m = message(open_dataset(dir.path()).map(|_| ()).unwrap_err());
        assert!(m.contains("0000001_diffuse.png"), "{m}");
    }

    #[test]
    fn crops() {
        let s = varied(16);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let mut offsets = std::collections::HashSet::new();
        for _ in 0..200 {
            let c = random_crop(&s, 5, &mut rng).unwrap();
            assert_eq!((c.height(), c.width(), c.roughness.channels), (5, 5, 1));
            // Locate the crop through the (unique) roughness/diffuse pattern.
            let found = (0..=11)
                .flat_map(|t| (0..=11).map(move |l| (t, l)))
                .find(|&(t, l)| s.crop(t, l, 5, 5).unwrap() == c)
                .expect("crop is a window of the material");
            offsets.insert(found);
        }
        // All 144 offsets are reachable; 200 draws hit most of them.
        assert!(offsets.len() > 60, "{}", offsets.len());
        assert!(offsets.iter().any(|&(t, _)| t == 11) && offsets.iter().any(|&(_, l)| l == 0));
        let full = random_crop(&s, 16, &mut rng).unwrap();
        assert_eq!(full, s);
        let m = message(random_crop(&s, 17, &mut rng).unwrap_err());
        assert!(m.contains("17x17") && m.contains("16x16"), "{m}");
        let c = center_crop(&s, 6).unwrap();
        assert_eq!(c, s.crop(5, 5, 6, 6).unwrap());
        let wide = Svbrdf::uniform(4, 10, [0.1; 3], [0.1; 3], 0.5);
        assert!(message(center_crop(&wide, 5).unwrap_err()).contains("10x4"));
        assert!(center_crop(&s, 0).is_err());
    }

    #[test]
    fn sources_are_usable_as_shared_trait_objects() {
        fn assert_send_sync<T: Send + Sync + ?Sized>() {}
        assert_send_sync::<dyn SvbrdfSource>();
        assert_send_sync::<MatfusionDataset>();
        assert_send_sync::<MaterialDirsDataset>();
        assert_send_sync::<StripDataset>();
    }
}
