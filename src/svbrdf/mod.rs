//! Spatially-varying GGX BRDFs: the material maps, their encodings, and the
//! paper's renderer (REFERENCE section 2) as batched tensor ops (`render`)
//! and as a scalar oracle (`scalar`); height fields and the shadows they
//! cast (`height`, `shadow`).

pub mod cpu;
pub mod ggx;
pub mod height;
pub mod render;
pub mod rows;
pub mod scalar;
pub mod shadow;

use crate::image::Image;
use anyhow::{bail, Result};

/// Number of channels of the stacked map tensor: kd(3) ks(3) roughness(1) normal(3).
pub const MAP_CHANNELS: usize = 10;
/// The roughness channel of the stacked map tensor.
pub const ROUGHNESS_CHANNEL: i64 = 6;

/// One material: linear maps on an H x W grid.
#[derive(Clone, Debug, PartialEq)]
pub struct Svbrdf {
    /// Linear diffuse albedo kd, `[3, H, W]`.
    pub diffuse: Image,
    /// Linear specular albedo ks (F0), `[3, H, W]`.
    pub specular: Image,
    /// GGX roughness r (alpha = r^2), `[1, H, W]`, in [0, 1].
    pub roughness: Image,
    /// Unit shading normals, `[3, H, W]`, z > 0.
    pub normal: Image,
    /// Height field the normals came from (plane units, [-1,1] spans the
    /// material), `[1, H, W]`, when known. Used for shadows.
    pub height_field: Option<Image>,
}

impl Svbrdf {
    pub fn height(&self) -> usize {
        self.diffuse.height
    }
    pub fn width(&self) -> usize {
        self.diffuse.width
    }

    /// Checks channel counts, equal sizes and finite values.
    pub fn validate(&self) -> Result<()> {
        let (h, w) = (self.height(), self.width());
        for (name, im, c) in [
            ("diffuse", &self.diffuse, 3),
            ("specular", &self.specular, 3),
            ("roughness", &self.roughness, 1),
            ("normal", &self.normal, 3),
        ] {
            if im.channels != c {
                bail!("{name} map has {} channels, expected {c}", im.channels);
            }
            if im.height != h || im.width != w {
                bail!("{name} map is {}x{}, the diffuse map is {w}x{h}", im.width, im.height);
            }
            if let Some((c, y, x)) = im.find_non_finite() {
                bail!("{name} map has a NaN/Inf value at channel {c}, row {y}, column {x}");
            }
        }
        Ok(())
    }

    /// The maps stacked as `[10, H, W]`: kd, ks, roughness, normal.
    pub fn stacked(&self) -> Image {
        Image::concat_channels(&[&self.diffuse, &self.specular, &self.roughness, &self.normal])
            .expect("validated maps share their size")
    }

    /// Inverse of [`Svbrdf::stacked`].
    pub fn from_stacked(maps: &Image) -> Result<Self> {
        if maps.channels != MAP_CHANNELS {
            bail!("stacked maps have {} channels, expected {MAP_CHANNELS}", maps.channels);
        }
        Ok(Self {
            diffuse: maps.channel_range(0, 3)?,
            specular: maps.channel_range(3, 3)?,
            roughness: maps.channel_range(6, 1)?,
            normal: maps.channel_range(7, 3)?,
            height_field: None,
        })
    }

    /// Crop of every map (and the height field). The crop's shorter side
    /// spans [-1,1] again (`geometry::half_extents`), so its pixels are wider
    /// in plane units: heights are scaled by the ratio of the shorter sides
    /// to keep the slopes the (unchanged) normals describe.
    pub fn crop(&self, top: usize, left: usize, h: usize, w: usize) -> Result<Self> {
        let scale = self.width().min(self.height()) as f32 / w.min(h).max(1) as f32;
        Ok(Self {
            diffuse: self.diffuse.crop(top, left, h, w)?,
            specular: self.specular.crop(top, left, h, w)?,
            roughness: self.roughness.crop(top, left, h, w)?,
            normal: self.normal.crop(top, left, h, w)?,
            height_field: self.height_field.as_ref().map(|hf| hf.crop(top, left, h, w).map(|c| c.map(|v| v * scale))).transpose()?,
        })
    }

    /// The maps of pixel (row `y`, column `x`) as a scalar-oracle material.
    pub fn pixel_material(&self, y: usize, x: usize) -> scalar::PixelMaterial {
        let px = |im: &Image| [0, 1, 2].map(|c| im.get(c, y, x) as f64);
        scalar::PixelMaterial {
            kd: px(&self.diffuse),
            ks: px(&self.specular),
            roughness: self.roughness.get(0, y, x) as f64,
            normal: px(&self.normal),
        }
    }

    /// One of the 8 symmetries of the square (data augmentation for a
    /// material bank): bit 0 mirrors x (columns), bit 1 mirrors y (rows),
    /// bit 2 then transposes rows and columns, applied as in
    /// [`Image::dihedral`]. The normals turn with the plane: a mirror negates
    /// the component across it; the transpose is the reflection across the
    /// line y = -x (rows run towards -y), so (n_x, n_y) -> (-n_y, -n_x).
    /// The result renders as the original would under the same transform of
    /// the light and camera ([`dihedral_point`]).
    pub fn dihedral(&self, code: u8) -> Self {
        let mut normal = self.normal.dihedral(code);
        let n = normal.height * normal.width;
        let (xs, rest) = normal.data.split_at_mut(n);
        let ys = &mut rest[..n];
        for (x, y) in xs.iter_mut().zip(ys.iter_mut()) {
            // Sign flips and swaps only: exact in f32 through f64.
            let [nx, ny, _] = dihedral_point(code, [*x as f64, *y as f64, 0.0]);
            (*x, *y) = (nx as f32, ny as f32);
        }
        Self {
            diffuse: self.diffuse.dihedral(code),
            specular: self.specular.dihedral(code),
            roughness: self.roughness.dihedral(code),
            normal,
            height_field: self.height_field.as_ref().map(|h| h.dihedral(code)),
        }
    }

    /// The same material in another colour: the diffuse and specular maps'
    /// chroma (in display space, gamma 2.2, where hue steps look even) is
    /// turned by `hue_turns` of a full turn about the grey axis and scaled
    /// by `saturation`; grey stays grey and every pixel keeps its display
    /// mean. Results are clamped to [0, 1]. Training augmentation: chroma
    /// must then be read from the photo, not guessed from the texture.
    pub fn recolour(&self, hue_turns: f32, saturation: f32) -> Self {
        let (sin, cos) = (std::f32::consts::TAU * hue_turns).sin_cos();
        let recolour_map = |map: &Image| {
            let n = map.height * map.width;
            let mut out = map.clone();
            for i in 0..n {
                let display = [0, 1, 2].map(|c| map.data[c * n + i].max(0.0).powf(1.0 / 2.2));
                let grey = (display[0] + display[1] + display[2]) / 3.0;
                let chroma = display.map(|v| v - grey);
                // Rodrigues about the unit grey axis a = (1,1,1)/sqrt(3); chroma is
                // perpendicular to a, so R v = cos v + sin (a x v).
                let k = 1.0 / 3f32.sqrt();
                let cross = [k * (chroma[2] - chroma[1]), k * (chroma[0] - chroma[2]), k * (chroma[1] - chroma[0])];
                for c in 0..3 {
                    let turned = cos * chroma[c] + sin * cross[c];
                    out.data[c * n + i] = (grey + saturation * turned).clamp(0.0, 1.0).powf(2.2);
                }
            }
            out
        };
        Self { diffuse: recolour_map(&self.diffuse), specular: recolour_map(&self.specular), ..self.clone() }
    }

    /// A uniform material (handy in tests and examples).
    pub fn uniform(h: usize, w: usize, kd: [f32; 3], ks: [f32; 3], roughness: f32) -> Self {
        Self {
            diffuse: Image::from_fn(3, h, w, |c, _, _| kd[c]),
            specular: Image::from_fn(3, h, w, |c, _, _| ks[c]),
            roughness: Image::filled(1, h, w, roughness),
            normal: Image::from_fn(3, h, w, |c, _, _| if c == 2 { 1.0 } else { 0.0 }),
            height_field: None,
        }
    }
}

/// Where a light or camera position goes under [`Svbrdf::dihedral`]`(code)`.
pub fn dihedral_point(code: u8, p: [f64; 3]) -> [f64; 3] {
    let (mut x, mut y) = (p[0], p[1]);
    if code & 1 != 0 {
        x = -x;
    }
    if code & 2 != 0 {
        y = -y;
    }
    if code & 4 != 0 {
        (x, y) = (-y, -x);
    }
    [x, y, p[2]]
}

/// Decodes a normal-map pixel c in [0,1]^3 to a unit vector: normalize(2c - 1).
pub fn decode_normal(c: [f32; 3]) -> [f32; 3] {
    crate::geometry::normalize3([2.0 * c[0] - 1.0, 2.0 * c[1] - 1.0, 2.0 * c[2] - 1.0])
}

/// Rescales every pixel of a `[3, H, W]` normal field to unit length (after
/// resampling, which shortens averaged normals).
pub fn renormalize_normals(normals: &Image) -> Image {
    let mut out = normals.clone();
    let n = normals.height * normals.width;
    for i in 0..n {
        let u = crate::geometry::normalize3([normals.data[i], normals.data[n + i], normals.data[2 * n + i]]);
        for c in 0..3 {
            out.data[c * n + i] = u[c];
        }
    }
    out
}

/// Encodes a unit normal to a normal-map pixel: (n + 1) / 2.
pub fn encode_normal(n: [f32; 3]) -> [f32; 3] {
    [(n[0] + 1.0) * 0.5, (n[1] + 1.0) * 0.5, (n[2] + 1.0) * 0.5]
}

/// Decodes a `[3, H, W]` normal-map image (values in [0,1]) to unit normals.
pub fn decode_normal_map(encoded: &Image) -> Image {
    renormalize_normals(&encoded.map(|c| 2.0 * c - 1.0))
}

/// Encodes unit normals `[3, H, W]` as a normal-map image in [0,1].
pub fn encode_normal_map(normals: &Image) -> Image {
    normals.map(|v| ((v + 1.0) * 0.5).clamp(0.0, 1.0))
}

/// Normals from a height field by central differences. `height` is in plane
/// units, where the material spans [-1,1] (so a pixel is 2/W wide).
/// Image rows go down while y goes up, hence the sign on dh/dy.
pub fn normals_from_height(height: &Image) -> Image {
    let (h, w) = (height.height, height.width);
    let (px, py) = (2.0 / w as f32, 2.0 / h as f32);
    let mut out = Image::new(3, h, w);
    for y in 0..h {
        for x in 0..w {
            let xl = x.saturating_sub(1);
            let xr = (x + 1).min(w - 1);
            let yu = y.saturating_sub(1);
            let yd = (y + 1).min(h - 1);
            let dhdx = (height.get(0, y, xr) - height.get(0, y, xl)) / (px * (xr - xl).max(1) as f32);
            // Row index grows downward, y coordinate grows upward.
            let dhdy = (height.get(0, yu, x) - height.get(0, yd, x)) / (py * (yd - yu).max(1) as f32);
            let (nx, ny, nz) = (-dhdx, -dhdy, 1.0f32);
            let len = (nx * nx + ny * ny + nz * nz).sqrt();
            out.set(0, y, x, nx / len);
            out.set(1, y, x, ny / len);
            out.set(2, y, x, nz / len);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A third of a turn about the grey axis sends red to green, two thirds
    /// to blue (hand-derived: the rotation by 120 degrees about (1,1,1)
    /// permutes the axes); grey and the specular F0 of a dielectric do not change;
    /// saturation 0 makes every pixel its display grey.
    #[test]
    fn recolour_turns_hue_about_grey() {
        let pixel = |m: &Image| [0, 1, 2].map(|c| m.get(c, 0, 0));
        let red = Svbrdf::uniform(2, 2, [0.6, 0.0, 0.0], [0.04; 3], 0.5);
        let turned = red.recolour(1.0 / 3.0, 1.0);
        let got = pixel(&turned.diffuse);
        for (g, want) in got.iter().zip([0.0, 0.6, 0.0]) {
            assert!((g - want).abs() < 1e-5, "{got:?}");
        }
        let twice = pixel(&red.recolour(2.0 / 3.0, 1.0).diffuse);
        assert!(twice.iter().zip([0.0, 0.0, 0.6]).all(|(g, w)| (g - w).abs() < 1e-5), "{twice:?}");
        let back = red.recolour(1.0, 1.0);
        assert!(pixel(&back.diffuse).iter().zip([0.6, 0.0, 0.0]).all(|(g, w)| (g - w).abs() < 1e-5));
        for c in pixel(&turned.specular) {
            assert!((c - 0.04).abs() < 1e-6);
        }
        let grey = Svbrdf::uniform(1, 1, [0.3, 0.3, 0.3], [0.04; 3], 0.5).recolour(0.37, 1.6);
        assert!(pixel(&grey.diffuse).iter().all(|c| (c - 0.3).abs() < 1e-6));
        // Saturation 0: the display mean of (0.6, 0, 0) is 0.6^(1/2.2) / 3.
        let flat = red.recolour(0.0, 0.0);
        let want = (0.6f32.powf(1.0 / 2.2) / 3.0).powf(2.2);
        assert!(pixel(&flat.diffuse).iter().all(|c| (c - want).abs() < 1e-6));
        assert_eq!(flat.roughness.data, red.roughness.data);
        assert_eq!(flat.normal.data, red.normal.data);
    }

    /// Rendering a transformed material under transformed light and camera
    /// gives the transformed render, for all 8 symmetries (normals,
    /// pixel grid and positions turn together).
    #[test]
    fn dihedral_transform_commutes_with_rendering() {
        use crate::geometry::LightView;
        let m = crate::data::procedural::generate(7, &crate::data::procedural::ProceduralConfig::with_size(24));
        let config = LightView { light: [0.7, -0.4, 2.5], view: [-0.3, 0.5, 3.0] };
        let reference = crate::svbrdf::render::render_material(&m, &[config]).unwrap().remove(0);
        for code in 0..8u8 {
            let moved = LightView { light: dihedral_point(code, config.light), view: dihedral_point(code, config.view) };
            let render = crate::svbrdf::render::render_material(&m.dihedral(code), &[moved]).unwrap().remove(0);
            let expected = reference.dihedral(code);
            let worst = render.data.iter().zip(&expected.data).map(|(a, b)| (a - b).abs() / (1e-3 + b.abs())).fold(0f32, f32::max);
            assert!(worst < 1e-4, "code {code}: relative difference {worst}");
        }
        // The transform is not the identity (except code 0), and 8 codes give 8 different materials.
        let firsts: std::collections::HashSet<Vec<u32>> = (0..8u8).map(|c| m.dihedral(c).normal.data[..30].iter().map(|v| v.to_bits()).collect()).collect();
        assert_eq!(firsts.len(), 8);
    }

    #[test]
    fn normal_codec_round_trip() {
        let n = decode_normal([0.5, 0.5, 1.0]);
        assert!((n[2] - 1.0).abs() < 1e-7 && n[0].abs() < 1e-7);
        let v = [0.6f32, -0.0, 0.8];
        let back = decode_normal(encode_normal(v));
        for i in 0..3 {
            assert!((back[i] - v[i]).abs() < 1e-6);
        }
    }

    #[test]
    fn stacked_round_trip() {
        let s = Svbrdf::uniform(4, 5, [0.1, 0.2, 0.3], [0.04, 0.05, 0.06], 0.5);
        s.validate().unwrap();
        let st = s.stacked();
        assert_eq!((st.channels, st.height, st.width), (10, 4, 5));
        assert_eq!(Svbrdf::from_stacked(&st).unwrap(), s);
    }

    #[test]
    fn tilted_plane_normals() {
        // h = 0.5 x: dh/dx = 0.5, so n = normalize(-0.5, 0, 1)
        let w = 16;
        let hf = Image::from_fn(1, w, w, |_, _, x| 0.5 * (2.0 * (x as f32 + 0.5) / w as f32 - 1.0));
        let n = normals_from_height(&hf);
        let len = (0.25f32 + 1.0).sqrt();
        assert!((n.get(0, 5, 7) + 0.5 / len).abs() < 1e-5);
        assert!(n.get(1, 5, 7).abs() < 1e-6);
        // h = 0.5 y (y up = row decreasing): n = normalize(0, -0.5, 1)
        let hf = Image::from_fn(1, w, w, |_, r, _| 0.5 * (1.0 - 2.0 * (r as f32 + 0.5) / w as f32));
        let n = normals_from_height(&hf);
        assert!((n.get(1, 5, 7) + 0.5 / len).abs() < 1e-5);
    }

    #[test]
    fn crop_keeps_heights_consistent_with_normals() {
        let n = 32;
        let hf = Image::from_fn(1, n, n, |_, r, c| 0.05 * ((r as f32 * 0.4).sin() + (c as f32 * 0.3).cos()));
        let mut s = Svbrdf::uniform(n, n, [0.5; 3], [0.04; 3], 0.5);
        s.normal = normals_from_height(&hf);
        s.height_field = Some(hf);
        let c = s.crop(4, 8, 16, 16).unwrap();
        let from_heights = normals_from_height(c.height_field.as_ref().unwrap());
        // Interior pixels (the border uses one-sided differences in both).
        for y in 1..15 {
            for x in 1..15 {
                for ch in 0..3 {
                    assert_eq!(from_heights.get(ch, y, x), c.normal.get(ch, y, x));
                }
            }
        }
    }

    #[test]
    fn validate_rejects_mismatch_and_nan() {
        let mut s = Svbrdf::uniform(4, 4, [0.1; 3], [0.04; 3], 0.5);
        s.roughness = Image::filled(1, 4, 3, 0.5);
        assert!(s.validate().unwrap_err().to_string().contains("roughness"));
        let mut s = Svbrdf::uniform(4, 4, [0.1; 3], [0.04; 3], 0.5);
        s.diffuse.data[3] = f32::INFINITY;
        assert!(s.validate().unwrap_err().to_string().contains("NaN/Inf"));
    }
}
