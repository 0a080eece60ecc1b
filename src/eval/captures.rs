//! Reader for real captures of one flat material: a folder with photos
//! `NN.png` (numbered; sorted by number), `camera_pos.txt` and
//! `light_pos.txt` (one `x,y,z` per line, one line per photo, in photo
//! order) and `image_size.txt` (the sample's width: the unit of the
//! positions). The origin is the sample centre, z points out of it.
//!
//! Positions are converted to flashmat units, where the material spans
//! [-1, 1]: divided by width / 2.
//!
//! (Comparing renders against the real photos, with the photos' 1/r^2
//! fall-off compensated, is not implemented yet.)

use anyhow::{anyhow, bail, ensure, Result};
use std::path::{Path, PathBuf};

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
}

impl Captures {
    /// Reads and checks a capture folder. Errors are one line naming the
    /// file at fault.
    pub fn open(dir: &Path) -> Result<Self> {
        ensure!(dir.is_dir(), "capture folder {} does not exist", dir.display());
        let photos = numbered_photos(dir)?;
        let size_path = dir.join("image_size.txt");
        let size_text = read_text(&size_path)?;
        let sample_width: f64 = size_text
            .trim()
            .parse()
            .map_err(|_| anyhow!("{}: expected one number (the sample's width), got '{}'", size_path.display(), size_text.trim()))?;
        ensure!(sample_width.is_finite() && sample_width > 0.0, "{}: the sample's width must be > 0, got {sample_width}", size_path.display());
        let scale = 2.0 / sample_width;
        let cameras = read_positions(&dir.join("camera_pos.txt"), scale, photos.len())?;
        let lights = read_positions(&dir.join("light_pos.txt"), scale, photos.len())?;
        Ok(Self { dir: dir.to_path_buf(), photos, cameras, lights, sample_width })
    }

    /// Index of the photo taken closest to straight overhead: the camera
    /// with the smallest angle to +z (the first one on ties).
    pub fn overhead(&self) -> usize {
        let cos = |c: &[f64; 3]| c[2] / (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
        let mut best = 0;
        for (i, c) in self.cameras.iter().enumerate() {
            if cos(c) > cos(&self.cameras[best]) {
                best = i;
            }
        }
        best
    }
}

fn read_text(path: &Path) -> Result<String> {
    std::fs::read_to_string(path).map_err(|e| anyhow!("cannot read {}: {e}", path.display()))
}

/// `NN.png` files of `dir` sorted by number; errors when there are none.
fn numbered_photos(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut found: Vec<(u64, PathBuf)> = Vec::new();
    for p in crate::io::sorted_entries(dir)? {
        let is_png = p.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case("png"));
        if let (true, Some(n)) = (is_png, p.file_stem().and_then(|s| s.to_str()).and_then(|s| s.parse::<u64>().ok())) {
            found.push((n, p));
        }
    }
    ensure!(!found.is_empty(), "no numbered photos (00.png, 01.png ...) in capture folder {}", dir.display());
    found.sort();
    if let Some(w) = found.windows(2).find(|w| w[0].0 == w[1].0) {
        bail!("capture folder {}: photos {} and {} have the same number", dir.display(), w[0].1.display(), w[1].1.display());
    }
    Ok(found.into_iter().map(|(_, p)| p).collect())
}

/// Parses one `x,y,z` per non-empty line, scaled by `scale`; there must be
/// `expected` lines and every z must be > 0.
fn read_positions(path: &Path, scale: f64, expected: usize) -> Result<Vec<[f64; 3]>> {
    let text = read_text(path)?;
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate() {
        if line.trim().is_empty() {
            continue;
        }
        let v: crate::cli::Vec3Arg =
            line.parse().map_err(|e: String| anyhow!("{} line {}: {e}", path.display(), i + 1))?;
        ensure!(v.0[2] > 0.0, "{} line {}: z must be > 0 (above the sample), got '{}'", path.display(), i + 1, line.trim());
        out.push(v.0.map(|c| c * scale));
    }
    ensure!(
        out.len() == expected,
        "{} has {} positions but the folder has {expected} photos (one line per photo)",
        path.display(),
        out.len()
    );
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

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

        let t = tempfile::tempdir().unwrap();
        fixture(t.path(), 2, "0,0,4\n0,0,5\n", "0,0,4\n0,0,5\n", "2");
        std::fs::remove_file(t.path().join("light_pos.txt")).unwrap();
        assert!(err(t.path()).contains("cannot read") && err(t.path()).contains("light_pos.txt"));

        let t = tempfile::tempdir().unwrap();
        assert!(err(t.path()).contains("no numbered photos"));
        assert!(err(&t.path().join("nope")).contains("does not exist"));
    }
}
