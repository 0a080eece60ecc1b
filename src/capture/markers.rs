//! Finding the frame's tags in a photo: the AprilTag C library's detector
//! (the `apriltag` crate) on the photo's grey values.

use apriltag::{Detector, DetectorBuilder, Family, Image as TagImage};

/// Decimation of the detector's quad search: the quads are found at half
/// resolution, their edges refined at full resolution (the library's
/// `refine_edges`), so the corners keep full-resolution accuracy.
const QUAD_DECIMATE: f32 = 2.0;
/// Below this many pixels on the shorter side, no decimation.
const DECIMATE_ABOVE_SIDE: usize = 1200;
/// Bits a detection may have wrong (the library's default for 36h11 is 2;
/// 1 keeps false positives off printed text).
const BITS_CORRECTED: usize = 1;

/// One detected tag: its id and its black square's corners in pixels
/// (x along columns, y down rows; a pixel's centre at +0.5), in the
/// detector's order (see [`super::frame::FrameLayout::corners`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Marker {
    pub id: u32,
    pub corners: [[f64; 2]; 4],
    /// The detector's decision margin (higher: clearer).
    pub margin: f32,
}

/// Grey values of an 8-bit photo, row-major.
pub struct Gray<'a> {
    pub width: usize,
    pub height: usize,
    pub values: &'a [u8],
}

fn detector(family: Family, side: usize, threads: usize) -> Option<Detector> {
    let mut d = DetectorBuilder::new().add_family_bits(family, BITS_CORRECTED).build().ok()?;
    d.set_decimation(if side > DECIMATE_ABOVE_SIDE { QUAD_DECIMATE } else { 1.0 });
    d.set_refine_edges(true);
    d.set_thread_number(threads.clamp(1, 16) as u8);
    Some(d)
}

fn to_tag_image(gray: &Gray) -> Option<TagImage> {
    let mut image = TagImage::zeros_with_stride(gray.width, gray.height, gray.width.next_multiple_of(96)).ok()?;
    let stride = image.stride();
    let buf = image.as_slice_mut();
    for (r, row) in gray.values.chunks_exact(gray.width).enumerate() {
        buf[r * stride..r * stride + gray.width].copy_from_slice(row);
    }
    Some(image)
}

/// The tag36h11 tags in a photo (the library's corners already put pixel
/// centres at +0.5: `capture::tests` checks them against projections).
pub fn detect(gray: &Gray, threads: usize) -> Vec<Marker> {
    let (Some(image), Some(mut d)) = (to_tag_image(gray), detector(Family::tag_36h11(), gray.width.min(gray.height), threads)) else {
        return vec![];
    };
    d.detect(&image)
        .into_iter()
        .map(|m| Marker { id: m.id() as u32, corners: m.corners(), margin: m.decision_margin() })
        .collect()
}

/// Names of other common tag families seen in a photo (for the error that
/// says the frame is not flashmat's): at least `min_count` of a family's
/// tags decoded with no bit wrong. tag16h5 is left out: its short codes
/// turn up in blurred tag36h11 tags.
pub fn other_families(gray: &Gray, threads: usize, min_count: usize) -> Vec<&'static str> {
    let Some(image) = to_tag_image(gray) else { return vec![] };
    let side = gray.width.min(gray.height);
    [("tag25h9", Family::tag_25h9()), ("tagStandard41h12", Family::tag_standard_41h12())]
        .into_iter()
        .filter_map(|(name, family)| {
            let mut d = detector(family, side, threads)?;
            (d.detect(&image).iter().filter(|m| m.hamming() == 0).count() >= min_count).then_some(name)
        })
        .collect()
}

/// Sharpness of a photo: how steep its steepest edges are, as the 99.9th
/// percentile of the grey gradient (central differences) over the spread
/// of grey values (1st to 99th percentile), per pixel, in a centred window
/// of at most 1024 x 1024 pixels. A sharp black-on-white edge gives about
/// 0.5, one blurred by a Gaussian of sigma pixels 0.4 / sigma; sensor noise
/// alone stays near 0.03.
pub fn sharpness(gray: &Gray) -> f64 {
    let (w, h) = (gray.width, gray.height);
    if w < 3 || h < 3 {
        return 0.0;
    }
    let (x0, y0) = (w.saturating_sub(1024) / 2, h.saturating_sub(1024) / 2);
    let (x1, y1) = ((x0 + 1024).min(w - 1), (y0 + 1024).min(h - 1));
    let at = |x: usize, y: usize| gray.values[y * w + x] as f64;
    let mut gradients = Vec::new();
    let mut levels = [0usize; 256];
    for y in y0.max(1)..y1 {
        for x in x0.max(1)..x1 {
            let gx = (at(x + 1, y) - at(x - 1, y)) / 2.0;
            let gy = (at(x, y + 1) - at(x, y - 1)) / 2.0;
            gradients.push(gx.hypot(gy));
            levels[gray.values[y * w + x] as usize] += 1;
        }
    }
    let n = gradients.len();
    let level = |q: f64| {
        let target = (q * n as f64) as usize;
        let mut seen = 0;
        levels.iter().position(|&c| {
            seen += c;
            seen > target
        })
        .unwrap_or(255) as f64
    };
    let spread = (level(0.99) - level(0.01)).max(1.0);
    let k = ((n as f64 * 0.999) as usize).min(n - 1);
    let (_, steep, _) = gradients.select_nth_unstable_by(k, f64::total_cmp);
    *steep / spread
}
