//! A minimal DNG writer: uncompressed, one image, little-endian TIFF, the
//! tags a RAW reader needs (DNG 1.4 spec) and nothing else. For the tests
//! (files whose pixels are known exactly) and for synthetic captures whose
//! photos are RAW (`data::captures`); flashmat never writes a user's photo
//! as DNG. Always compiled: reading needs the `raw` feature, writing does
//! not.
//!
//! The camera is a linear sRGB sensor with a white balance: a pixel of
//! linear sRGB value v (D65 white) is stored as black + v * neutral_c *
//! (white - black), so a reader that divides by the file's AsShotNeutral
//! and applies its ColorMatrix1 (XYZ -> camera: XYZ -> linear sRGB here)
//! gets v back. Bayer files keep one colour a pixel (RGGB).

use crate::image::Image;
use anyhow::{ensure, Result};
use std::path::Path;

/// How [`write_dng`] stores a linear image.
#[derive(Clone, Debug)]
pub struct DngOptions {
    /// Bits a sample (white level 2^bits - 1): 10 to 16.
    pub bits: u32,
    /// Black level, in codes.
    pub black: u32,
    /// One colour a pixel in an RGGB mosaic (`PhotometricInterpretation`
    /// CFA), else three (`LinearRaw`, as Apple ProRAW).
    pub bayer: bool,
    /// The camera's neutral (AsShotNeutral): raw = linear x neutral.
    pub neutral: [f64; 3],
    /// BaselineExposure, stops: how far a reader brightens the file's
    /// linear values for a normal exposure.
    pub baseline_exposure: f64,
    /// EXIF orientation 1..=8.
    pub orientation: u16,
    /// 35 mm-equivalent focal length (EXIF FocalLengthIn35mmFilm), mm.
    pub focal_35mm: Option<u16>,
    /// A lens-shading gain map (OpcodeList2 GainMap, one plane for all
    /// colours): `(rows, cols, gains)` over the image, row-major. The
    /// stored values are divided by it, so a reader that applies it gets
    /// the image back.
    pub gain_map: Option<(usize, usize, Vec<f32>)>,
}

impl Default for DngOptions {
    fn default() -> Self {
        Self { bits: 12, black: 64, bayer: false, neutral: [0.5, 1.0, 0.7], baseline_exposure: 0.0, orientation: 1, focal_35mm: None, gain_map: None }
    }
}

/// XYZ (D65) -> linear sRGB, IEC 61966-2-1: the camera's ColorMatrix1.
const XYZ_TO_SRGB: [f64; 9] = [3.2404542, -1.5371385, -0.4985314, -0.9692660, 1.8760108, 0.0415560, 0.0556434, -0.2040259, 1.0572252];

/// TIFF field types.
const BYTE: u16 = 1;
const ASCII: u16 = 2;
const SHORT: u16 = 3;
const LONG: u16 = 4;
const RATIONAL: u16 = 5;
const UNDEFINED: u16 = 7;
const SRATIONAL: u16 = 10;

/// One IFD entry: tag, type, count and the value's little-endian bytes.
struct Entry {
    tag: u16,
    kind: u16,
    count: u32,
    bytes: Vec<u8>,
}

fn shorts(tag: u16, v: &[u16]) -> Entry {
    Entry { tag, kind: SHORT, count: v.len() as u32, bytes: v.iter().flat_map(|x| x.to_le_bytes()).collect() }
}

fn longs(tag: u16, v: &[u32]) -> Entry {
    Entry { tag, kind: LONG, count: v.len() as u32, bytes: v.iter().flat_map(|x| x.to_le_bytes()).collect() }
}

fn bytes(tag: u16, kind: u16, v: &[u8]) -> Entry {
    Entry { tag, kind, count: v.len() as u32, bytes: v.to_vec() }
}

fn ascii(tag: u16, s: &str) -> Entry {
    let mut v = s.as_bytes().to_vec();
    v.push(0);
    bytes(tag, ASCII, &v)
}

/// Rationals with denominator 10^6 (signed when `signed`).
fn rationals(tag: u16, v: &[f64], signed: bool) -> Entry {
    let bytes = v
        .iter()
        .flat_map(|&x| {
            let num = (x * 1e6).round();
            let num = if signed { (num as i32).to_le_bytes() } else { (num as u32).to_le_bytes() };
            num.into_iter().chain(1_000_000u32.to_le_bytes())
        })
        .collect();
    Entry { tag, kind: if signed { SRATIONAL } else { RATIONAL }, count: v.len() as u32, bytes }
}

/// The DNG GainMap opcode (ID 9) over the whole image, one plane for all
/// colours: the OpcodeList2 bytes (big-endian, as the DNG spec says).
fn gain_map_opcodes(width: usize, height: usize, rows: usize, cols: usize, gains: &[f32], planes: u32) -> Vec<u8> {
    let mut p: Vec<u8> = Vec::new();
    for v in [0u32, 0, height as u32, width as u32, 0, planes, 1, 1, rows as u32, cols as u32] {
        p.extend(v.to_be_bytes());
    }
    // Spacing and origin (relative to the image): the map spans it corner to corner.
    let spacing = |n: usize| if n > 1 { 1.0 / (n - 1) as f64 } else { 1.0 };
    for v in [spacing(rows), spacing(cols), 0.0f64, 0.0] {
        p.extend(v.to_be_bytes());
    }
    p.extend(1u32.to_be_bytes()); // MapPlanes
    for g in gains {
        p.extend(g.to_be_bytes());
    }
    let mut list = Vec::new();
    list.extend(1u32.to_be_bytes()); // one opcode
    for v in [9u32, 0x0103_0000, 0, p.len() as u32] {
        list.extend(v.to_be_bytes());
    }
    list.extend(p);
    list
}

/// The gain map's value at a pixel centre, bilinear (as [`super::raw`]
/// reads it).
pub fn gain_at(rows: usize, cols: usize, gains: &[f32], y: usize, x: usize, height: usize, width: usize) -> f32 {
    let at = |pos: f64, n: usize| -> (usize, usize, f32) {
        let t = (pos * (n.max(2) - 1) as f64).clamp(0.0, (n - 1) as f64);
        let i = (t.floor() as usize).min(n.saturating_sub(2));
        let i1 = (i + 1).min(n - 1);
        (i, i1, (t - i as f64) as f32)
    };
    let (r0, r1, fy) = at((y as f64 + 0.5) / height as f64, rows);
    let (c0, c1, fx) = at((x as f64 + 0.5) / width as f64, cols);
    let g = |r: usize, c: usize| gains[r * cols + c];
    (g(r0, c0) * (1.0 - fx) + g(r0, c1) * fx) * (1.0 - fy) + (g(r1, c0) * (1.0 - fx) + g(r1, c1) * fx) * fy
}

/// Writes `linear` (`[3, H, W]`, linear sRGB, 1.0 at the white level) as a
/// DNG (values above 1 clip at the white level, as a sensor's).
pub fn write_dng(path: &Path, linear: &Image, opts: &DngOptions) -> Result<()> {
    ensure!(linear.channels == 3, "a DNG is written from 3 channels, got {}", linear.channels);
    ensure!((10..=16).contains(&opts.bits), "DNG samples are 10 to 16 bits, got {}", opts.bits);
    let white = (1u32 << opts.bits) - 1;
    ensure!(opts.black < white / 2, "the black level {} is above half the white level {white}", opts.black);
    ensure!(opts.neutral.iter().all(|&n| n > 0.0 && n <= 1.0), "the neutral must be in (0, 1], got {:?}", opts.neutral);
    let (w, h) = (linear.width, linear.height);
    ensure!(!opts.bayer || (w % 2 == 0 && h % 2 == 0), "a Bayer DNG needs even sides, got {w}x{h}");
    let spp: usize = if opts.bayer { 1 } else { 3 };
    let range = (white - opts.black) as f32;
    let code = |c: usize, y: usize, x: usize| -> u16 {
        let gain = opts.gain_map.as_ref().map_or(1.0, |(r, cl, g)| gain_at(*r, *cl, g, y, x, h, w));
        let v = linear.get(c, y, x) * opts.neutral[c] as f32 / gain;
        (opts.black as f32 + (v.max(0.0) * range).round()).min(white as f32) as u16
    };
    let mut pixels: Vec<u8> = Vec::with_capacity(w * h * spp * 2);
    for y in 0..h {
        for x in 0..w {
            if opts.bayer {
                // RGGB: red at (even, even), blue at (odd, odd).
                let c = match (y % 2, x % 2) {
                    (0, 0) => 0,
                    (1, 1) => 2,
                    _ => 1,
                };
                pixels.extend(code(c, y, x).to_le_bytes());
            } else {
                for c in 0..3 {
                    pixels.extend(code(c, y, x).to_le_bytes());
                }
            }
        }
    }
    let mut exif = vec![rationals(33434, &[1.0 / 60.0], false), rationals(33437, &[1.8], false), shorts(34855, &[100])];
    if let Some(f) = opts.focal_35mm {
        exif.push(shorts(41989, &[f]));
    }
    let mut root = vec![
        longs(254, &[0]),
        longs(256, &[w as u32]),
        longs(257, &[h as u32]),
        shorts(258, &vec![16; spp]),
        shorts(259, &[1]),
        shorts(262, &[if opts.bayer { 32803 } else { 34892 }]),
        ascii(271, "flashmat"),
        ascii(272, "synthetic linear sensor"),
        longs(273, &[0]), // StripOffsets: set below
        shorts(274, &[opts.orientation]),
        shorts(277, &[spp as u16]),
        longs(278, &[h as u32]),
        longs(279, &[pixels.len() as u32]),
        shorts(284, &[1]),
        longs(34665, &[0]), // ExifIFD: set below
        bytes(50706, BYTE, &[1, 4, 0, 0]),
        bytes(50707, BYTE, &[1, 1, 0, 0]),
        ascii(50708, "flashmat synthetic linear sensor"),
        longs(50714, &vec![opts.black; spp]),
        longs(50717, &vec![white; spp]),
        rationals(50721, &XYZ_TO_SRGB, true),
        rationals(50728, &opts.neutral, false),
        rationals(50730, &[opts.baseline_exposure], true),
        shorts(50778, &[21]),
    ];
    if opts.bayer {
        root.push(shorts(33421, &[2, 2]));
        root.push(bytes(33422, BYTE, &[0, 1, 1, 2]));
    }
    if let Some((rows, cols, gains)) = &opts.gain_map {
        ensure!(*rows >= 2 && *cols >= 2 && gains.len() == rows * cols, "a gain map needs at least 2x2 gains, rows x cols of them");
        root.push(bytes(51009, UNDEFINED, &gain_map_opcodes(w, h, *rows, *cols, gains, spp as u32)));
    }
    root.sort_by_key(|e| e.tag);
    exif.sort_by_key(|e| e.tag);
    // Layout: header, root IFD, its values, Exif IFD, its values, pixels.
    let ifd_size = |entries: &[Entry]| 2 + 12 * entries.len() + 4;
    let values_size = |entries: &[Entry]| entries.iter().filter(|e| e.bytes.len() > 4).map(|e| e.bytes.len().div_ceil(2) * 2).sum::<usize>();
    let root_at = 8;
    let exif_at = root_at + ifd_size(&root) + values_size(&root);
    let pixels_at = exif_at + ifd_size(&exif) + values_size(&exif);
    for e in root.iter_mut() {
        match e.tag {
            273 => e.bytes = (pixels_at as u32).to_le_bytes().to_vec(),
            34665 => e.bytes = (exif_at as u32).to_le_bytes().to_vec(),
            _ => {}
        }
    }
    let mut out: Vec<u8> = b"II*\0".to_vec();
    out.extend((root_at as u32).to_le_bytes());
    let write_ifd = |out: &mut Vec<u8>, entries: &[Entry], at: usize| {
        let mut values_at = at + ifd_size(entries);
        let mut values = Vec::new();
        out.extend((entries.len() as u16).to_le_bytes());
        for e in entries {
            out.extend(e.tag.to_le_bytes());
            out.extend(e.kind.to_le_bytes());
            out.extend(e.count.to_le_bytes());
            if e.bytes.len() <= 4 {
                let mut inline = e.bytes.clone();
                inline.resize(4, 0);
                out.extend(inline);
            } else {
                out.extend((values_at as u32).to_le_bytes());
                let mut v = e.bytes.clone();
                v.resize(v.len().div_ceil(2) * 2, 0);
                values_at += v.len();
                values.extend(v);
            }
        }
        out.extend(0u32.to_le_bytes()); // no next IFD
        out.extend(values);
    };
    write_ifd(&mut out, &root, root_at);
    debug_assert_eq!(out.len(), exif_at);
    write_ifd(&mut out, &exif, exif_at);
    debug_assert_eq!(out.len(), pixels_at);
    out.extend(pixels);
    super::atomic_write_bytes(path, &out)
}
