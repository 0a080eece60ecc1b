//! GGX values and directions as rows `[R, ...]`: the per-pixel samples a
//! teacher learns from (`train::teacher`) and a material's codes are
//! fitted to (`fit::codes`), and the GGX radiance of each row.

use super::render::render_directions;
use tch::{Device, Kind, Tensor};

/// Light and view directions `[R, 3]` each: cosine-distributed over the
/// hemisphere, a quarter of the views within a few degrees of the light
/// (the flash configuration).
pub fn random_directions(n: i64, device: Device) -> (Tensor, Tensor) {
    let opts = (Kind::Float, device);
    let cosine = |n: i64| {
        let u1 = Tensor::rand([n, 1], opts);
        let phi = Tensor::rand([n, 1], opts) * (2.0 * std::f64::consts::PI);
        let r = u1.sqrt();
        Tensor::cat(&[&r * phi.cos(), &r * phi.sin(), (1.0f64 - &u1).clamp_min(1e-4).sqrt()], 1)
    };
    let wi = cosine(n);
    let near = normalize_rows(&(&wi + Tensor::randn([n, 3], opts) * 0.05));
    let near = Tensor::cat(&[near.narrow(1, 0, 2), near.narrow(1, 2, 1).clamp_min(0.05)], 1);
    let near = normalize_rows(&near);
    let colocated = Tensor::rand([n, 1], opts).lt(0.25).to_kind(Kind::Float);
    let wo = normalize_rows(&(&colocated * near + (1.0 - &colocated) * cosine(n)));
    (wi, wo)
}

/// Lights inside each row's GGX lobe: the view `wo` mirrored about a half
/// vector drawn around the row's normal, `offsets` x 1.5 alpha along x and
/// y (alpha = roughness^2). maps: `[R, 10]` (kd, ks, roughness, normal);
/// wo: `[R, 3]` unit; offsets: `[R, 2]` standard normal draws -> (wi
/// `[R, 3]`, `[R, 1]` bool: the light is above the surface, z > 0.02).
pub fn lobe_lights(maps: &Tensor, wo: &Tensor, offsets: &Tensor) -> (Tensor, Tensor) {
    let alpha = maps.narrow(1, super::ROUGHNESS_CHANNEL, 1).square();
    let n = maps.size()[0];
    let shift = Tensor::cat(&[offsets * (&alpha * 1.5), Tensor::zeros([n, 1], (offsets.kind(), offsets.device()))], 1);
    let h = normalize_rows(&(maps.narrow(1, 7, 3) + shift));
    let mirrored = normalize_rows(&(&h * (wo * &h).sum_dim_intlist([1i64].as_slice(), true, Kind::Float) * 2.0 - wo));
    let above = mirrored.narrow(1, 2, 1).gt(0.02);
    (mirrored, above)
}

/// Rows `[R, D]` scaled to unit length.
pub fn normalize_rows(v: &Tensor) -> Tensor {
    v / v.square().sum_dim_intlist([1i64].as_slice(), true, Kind::Float).sqrt().clamp_min(1e-12)
}

/// ln(1 + R) of the GGX renderer for rows. maps `[R, 10]`, wi, wo `[R, 3]` -> `[R, 3]`.
pub fn ggx_log_rows(maps: &Tensor, wi: &Tensor, wo: &Tensor) -> Tensor {
    let n = maps.size()[0];
    let as_image = |t: &Tensor| t.transpose(0, 1).reshape([1, -1, n, 1]);
    let dirs = |t: &Tensor| as_image(t).unsqueeze(1); // [1, 1, 3, R, 1]
    let r = render_directions(&as_image(maps), &dirs(wi), &dirs(wo)); // [1, 1, 3, R, 1]
    r.reshape([3, n]).transpose(0, 1).clamp_min(0.0).log1p()
}

/// The loss of rows of ln(1 + R) (the teacher's, and the code fit's): the L1 of ln(1 + R), plus with `dark_floor` F > 0 the
/// L1 of ln(F + R) (the prediction's radiance clamped at 0 there; the first
/// term still pulls a negative one up). pred, target: ln(1 + R) `[R, 3]` -> scalar.
pub fn log_rows_loss(pred: &Tensor, target: &Tensor, dark_floor: f64) -> Tensor {
    let l1 = (pred - target).abs().mean(Kind::Float);
    if dark_floor <= 0.0 {
        return l1;
    }
    let relative = |log1p: &Tensor| (log1p.expm1().clamp_min(0.0) + dark_floor).log();
    l1 + (relative(pred) - relative(target)).abs().mean(Kind::Float)
}
