//! The held-out coloured-metal set (issue 83): materials whose colour is
//! in the specular, and saturated glossy dielectrics, the corner of GGX
//! space real captures land in (teal and gold metallic scales, a glossy
//! bathroom tile) and the procedural families rarely draw. Each is two
//! finishes laid out by a mask (checker, scales, leaf, crackle) with gentle
//! fbm bumps; every value is linear.

use super::noise::{fbm, worley, V2};
use crate::image::Image;
use crate::svbrdf::{normals_from_height, Svbrdf};

/// One finish: diffuse and specular albedo (linear) and roughness.
#[derive(Clone, Copy, Debug)]
struct Finish {
    kd: [f32; 3],
    ks: [f32; 3],
    roughness: f32,
}

/// How a material's two finishes are laid out.
#[derive(Clone, Copy, Debug)]
enum Layout {
    /// Squares of 8 per side.
    Checker,
    /// Overlapping round scales (Voronoi cells), alternate ones in the second finish.
    Scales,
    /// Leaf squares of 4 per side with fbm-torn edges and a few gaps of the second finish.
    Leaf,
    /// A glaze: the second finish in thin crackle lines between Voronoi cells.
    Crackle,
}

/// An 8-bit map value to linear, as flashmat reads a map PNG (the issue's
/// colours are PNG values).
fn srgb(c: [u8; 3]) -> [f32; 3] {
    c.map(|v| crate::spaces::gamma_decode(v as f32 / 255.0))
}

/// Names of the set, in index order.
pub const METAL_MATERIALS: [&str; 6] = ["gold-teal-checker", "gold-leaf", "copper-scales", "anodised-blue-red", "glazed-tile", "brushed-steel-brass"];

/// The finishes and layout of material `index` (< [`METAL_MATERIALS`]'s length).
fn recipe(index: usize) -> (Finish, Finish, Layout, f32) {
    let metal = |ks: [u8; 3], roughness: f32| Finish { kd: srgb([18, 18, 18]), ks: srgb(ks), roughness };
    match index {
        // The checker: diffuse 18/255, specular (235, 185, 80) and (60, 195, 185), roughness 90/255.
        0 => (metal([235, 185, 80], 90.0 / 255.0), metal([60, 195, 185], 90.0 / 255.0), Layout::Checker, 0.004),
        // Gold leaf on a red bole: sharp gold, the bole a matte red dielectric in the gaps.
        1 => (metal([245, 200, 90], 0.18), Finish { kd: srgb([150, 40, 30]), ks: [0.04; 3], roughness: 0.7 }, Layout::Leaf, 0.003),
        // Copper scales, alternate ones patinated darker and rougher.
        2 => (metal([240, 150, 110], 0.25), metal([190, 100, 70], 0.45), Layout::Scales, 0.006),
        // Anodised aluminium, blue and red, satin.
        3 => (metal([70, 110, 235], 0.3), metal([225, 60, 70], 0.3), Layout::Checker, 0.002),
        // A saturated green glazed tile, glossy, with a white crackle.
        4 => (Finish { kd: srgb([20, 120, 60]), ks: [0.05; 3], roughness: 0.08 }, Finish { kd: srgb([230, 230, 220]), ks: [0.04; 3], roughness: 0.5 }, Layout::Crackle, 0.002),
        // Steel and brass, brushed (rough).
        _ => (metal([200, 200, 205], 0.5), metal([225, 190, 110], 0.4), Layout::Scales, 0.004),
    }
}

/// Coloured-metal material `index` at `size x size`.
/// Panics on an index past the set ([`METAL_MATERIALS`]).
pub fn metal_material(index: usize, size: usize) -> Svbrdf {
    assert!(index < METAL_MATERIALS.len(), "the coloured-metal set has {} materials", METAL_MATERIALS.len());
    let (a, b, layout, bump) = recipe(index);
    let seed = 0xC0_10u32 + index as u32;
    let mut kd = Image::new(3, size, size);
    let mut ks = Image::new(3, size, size);
    let mut rough = Image::new(1, size, size);
    let mut height = Image::new(1, size, size);
    for y in 0..size {
        for x in 0..size {
            // The sample's width is 1 unit, so patterns keep their scale at any size.
            let p: V2 = [x as f32 / size as f32, y as f32 / size as f32];
            let (second, relief) = match layout {
                Layout::Checker => ((((p[0] * 8.0) as i32 + (p[1] * 8.0) as i32) % 2) == 1, 0.0),
                Layout::Scales => {
                    let cell = worley([p[0] * 7.0, p[1] * 7.0], seed, 0.8);
                    (cell.id % 2 == 1, -cell.f1)
                }
                Layout::Leaf => {
                    let torn = fbm([p[0] * 12.0, p[1] * 12.0], seed, 4, 0.5) * 0.08;
                    let (u, v) = ((p[0] * 4.0 + torn).fract(), (p[1] * 4.0 - torn).fract());
                    (u < 0.03 || v < 0.03, 0.0)
                }
                Layout::Crackle => {
                    let cell = worley([p[0] * 6.0, p[1] * 6.0], seed, 0.9);
                    (cell.f2 - cell.f1 < 0.04, 0.0)
                }
            };
            let f = if second { b } else { a };
            for c in 0..3 {
                kd.set(c, y, x, f.kd[c]);
                ks.set(c, y, x, f.ks[c]);
            }
            rough.set(0, y, x, f.roughness);
            let bumps = fbm([p[0] * 10.0, p[1] * 10.0], seed ^ 0x5a5a, 5, 0.5);
            height.set(0, y, x, bump * (bumps + relief * 0.5));
        }
    }
    let normal = normals_from_height(&height);
    Svbrdf { diffuse: kd, specular: ks, roughness: rough, normal, height_field: Some(height) }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_metals_keep_their_colour_in_the_specular() {
        for i in 0..METAL_MATERIALS.len() {
            let m = metal_material(i, 32);
            m.validate().unwrap();
            let mean = |im: &Image, c: usize| (0..32 * 32).map(|k| im.get(c, k / 32, k % 32) as f64).sum::<f64>() / 1024.0;
            let ks = [0, 1, 2].map(|c| mean(&m.specular, c));
            let kd = [0, 1, 2].map(|c| mean(&m.diffuse, c));
            // Every material has a coloured or bright specular or a saturated diffuse.
            let spread = |v: [f64; 3]| v.iter().cloned().fold(f64::MIN, f64::max) - v.iter().cloned().fold(f64::MAX, f64::min);
            assert!(spread(ks) > 0.05 || spread(kd) > 0.1, "{}: ks {ks:?} kd {kd:?}", METAL_MATERIALS[i]);
        }
        // The checker: (18/255)^2.2 = 0.00293 and (235/255)^2.2 = 0.8355; roughness 90/255.
        let m = metal_material(0, 64);
        assert!((m.diffuse.get(0, 0, 0) - 0.00293).abs() < 5e-5 && (m.specular.get(0, 0, 0) - 0.8355).abs() < 1e-3);
        assert!((m.roughness.get(0, 0, 0) - 90.0 / 255.0).abs() < 1e-6);
        // Its second square teal: green and blue above red.
        let (g, r) = (m.specular.get(1, 0, 12), m.specular.get(0, 0, 12));
        assert!(g > 4.0 * r, "teal square: r {r} g {g}");
    }
}
