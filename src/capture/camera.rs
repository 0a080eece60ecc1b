//! The camera of a capture: a pinhole with two radial distortion terms,
//! a pose per photo, a first guess from each photo's plane homography, and
//! their joint refinement over all photos (Levenberg-Marquardt on the tag
//! corners' reprojection error).
//!
//! Pixel coordinates: x along columns, y down rows, a pixel's centre at
//! +0.5. Camera coordinates: x right, y down, z forward (into the scene).
//! World coordinates: the frame's (mm, z out of the paper).
//! A pose maps world to camera: x_cam = R x_world + t.

use crate::geometry::{cross, dot, length, normalize, sub, Vec3};
use anyhow::{bail, ensure, Result};
use tch::{Kind, Tensor};

pub type Mat3 = [[f64; 3]; 3];

/// Focal length (pixels), principal point (pixels) and radial distortion:
/// a camera-space point (x, y, 1) lands at centre + focal * (x, y) * (1 +
/// k1 r^2 + k2 r^4), r^2 = x^2 + y^2.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    pub focal: f64,
    pub centre: [f64; 2],
    pub k1: f64,
    pub k2: f64,
}

impl Intrinsics {
    /// A distortion-free camera centred on a `width x height` photo.
    pub fn centred(focal: f64, width: usize, height: usize) -> Self {
        Self { focal, centre: [width as f64 / 2.0, height as f64 / 2.0], k1: 0.0, k2: 0.0 }
    }

    /// Pixel of the normalised image point (x, y).
    pub fn distort(&self, x: f64, y: f64) -> [f64; 2] {
        let r2 = x * x + y * y;
        let d = 1.0 + self.k1 * r2 + self.k2 * r2 * r2;
        [self.centre[0] + self.focal * d * x, self.centre[1] + self.focal * d * y]
    }

    /// Normalised image point of a pixel (the inverse of [`Self::distort`],
    /// by fixed-point iteration: exact to 1e-12 for the mild distortion of
    /// phone lenses).
    pub fn undistort(&self, pixel: [f64; 2]) -> [f64; 2] {
        let (xd, yd) = ((pixel[0] - self.centre[0]) / self.focal, (pixel[1] - self.centre[1]) / self.focal);
        let (mut x, mut y) = (xd, yd);
        for _ in 0..20 {
            let r2 = x * x + y * y;
            let d = 1.0 + self.k1 * r2 + self.k2 * r2 * r2;
            (x, y) = (xd / d, yd / d);
        }
        [x, y]
    }
}

/// World to camera: x_cam = rotation * x_world + translation.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    pub rotation: Mat3,
    pub translation: Vec3,
}

pub fn mat_vec(m: &Mat3, v: Vec3) -> Vec3 {
    [dot(m[0], v), dot(m[1], v), dot(m[2], v)]
}

pub fn transpose(m: &Mat3) -> Mat3 {
    std::array::from_fn(|i| std::array::from_fn(|j| m[j][i]))
}

pub fn mat_mul(a: &Mat3, b: &Mat3) -> Mat3 {
    std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| a[i][k] * b[k][j]).sum()))
}

impl Pose {
    /// A camera at `eye` looking at `target`, its image's up (-y) toward
    /// `up` as far as the view allows.
    pub fn look_at(eye: Vec3, target: Vec3, up: Vec3) -> Self {
        let z = normalize(sub(target, eye));
        let x = normalize(cross(z, up));
        let y = cross(z, x);
        let rotation = [x, y, z];
        Self { rotation, translation: mat_vec(&rotation, eye).map(|v| -v) }
    }

    /// The lens's position in the world.
    pub fn centre(&self) -> Vec3 {
        mat_vec(&transpose(&self.rotation), self.translation).map(|v| -v)
    }

    /// A camera-space direction in world space.
    pub fn to_world_dir(&self, d: Vec3) -> Vec3 {
        mat_vec(&transpose(&self.rotation), d)
    }

    /// The pixel a world point lands on (None behind the camera).
    pub fn project(&self, k: &Intrinsics, p: Vec3) -> Option<[f64; 2]> {
        let c = crate::geometry::add(mat_vec(&self.rotation, p), self.translation);
        (c[2] > 1e-9).then(|| k.distort(c[0] / c[2], c[1] / c[2]))
    }

    /// Where a pixel's ray meets the plane z = 0 (None if it does not).
    pub fn plane_point(&self, k: &Intrinsics, pixel: [f64; 2]) -> Option<[f64; 2]> {
        let [x, y] = k.undistort(pixel);
        let d = self.to_world_dir([x, y, 1.0]);
        let o = self.centre();
        let s = -o[2] / d[2];
        (s.is_finite() && s > 0.0).then(|| [o[0] + s * d[0], o[1] + s * d[1]])
    }
}

/// The rotation by the angle |w| (radians) about w (Rodrigues).
pub fn rotation_from_vector(w: Vec3) -> Mat3 {
    let angle = length(w);
    if angle < 1e-15 {
        return [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    }
    let [x, y, z] = w.map(|v| v / angle);
    let (s, c) = angle.sin_cos();
    let t = 1.0 - c;
    [[c + x * x * t, x * y * t - z * s, x * z * t + y * s], [y * x * t + z * s, c + y * y * t, y * z * t - x * s], [z * x * t - y * s, z * y * t + x * s, c + z * z * t]]
}

/// The angle between two rotations, degrees.
pub fn rotation_angle_deg(a: &Mat3, b: &Mat3) -> f64 {
    let m = mat_mul(a, &transpose(b));
    let trace = m[0][0] + m[1][1] + m[2][2];
    ((trace - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees()
}

fn tensor_of(rows: &[f64], n: i64, m: i64) -> Tensor {
    Tensor::from_slice(rows).view([n, m])
}

fn values(t: &Tensor) -> Vec<f64> {
    Vec::<f64>::try_from(t.to_kind(Kind::Double).flatten(0, -1)).expect("a CPU double tensor")
}

/// The rotation nearest to `m` (Frobenius): U V^T of its SVD, with the sign
/// that keeps det = +1.
pub fn nearest_rotation(m: &Mat3) -> Mat3 {
    let (u, _, v) = tensor_of(&m.concat(), 3, 3).svd(true, true);
    let vt = v.transpose(0, 1);
    let to_mat = |t: &Tensor| -> Mat3 {
        let r = values(t);
        std::array::from_fn(|i| std::array::from_fn(|j| r[i * 3 + j]))
    };
    let r = to_mat(&u.matmul(&vt));
    if dot(r[0], cross(r[1], r[2])) >= 0.0 {
        return r;
    }
    to_mat(&(u * Tensor::from_slice(&[1.0f64, 1.0, -1.0])).matmul(&vt))
}

/// The homography taking plane points to pixels, by the normalised direct
/// linear transform over `pairs` (plane point, pixel); at least 4 pairs.
pub fn homography(pairs: &[([f64; 2], [f64; 2])]) -> Result<Mat3> {
    ensure!(pairs.len() >= 4, "a homography needs 4 points, got {}", pairs.len());
    // Hartley normalisation: each side centred, mean distance sqrt(2).
    let normaliser = |pts: Vec<[f64; 2]>| {
        let n = pts.len() as f64;
        let mean = [pts.iter().map(|p| p[0]).sum::<f64>() / n, pts.iter().map(|p| p[1]).sum::<f64>() / n];
        let spread = pts.iter().map(|p| (p[0] - mean[0]).hypot(p[1] - mean[1])).sum::<f64>() / n;
        let s = std::f64::consts::SQRT_2 / spread.max(1e-12);
        [[s, 0.0, -s * mean[0]], [0.0, s, -s * mean[1]], [0.0, 0.0, 1.0]]
    };
    let tw = normaliser(pairs.iter().map(|p| p.0).collect());
    let ti = normaliser(pairs.iter().map(|p| p.1).collect());
    let mut rows = Vec::with_capacity(pairs.len() * 18);
    for (w, i) in pairs {
        let [x, y, _] = mat_vec(&tw, [w[0], w[1], 1.0]);
        let [u, v, _] = mat_vec(&ti, [i[0], i[1], 1.0]);
        rows.extend_from_slice(&[x, y, 1.0, 0.0, 0.0, 0.0, -u * x, -u * y, -u]);
        rows.extend_from_slice(&[0.0, 0.0, 0.0, x, y, 1.0, -v * x, -v * y, -v]);
    }
    // Full V (9 x 9): its last column spans the null space even for 4 points.
    let (_, s, v) = tensor_of(&rows, 2 * pairs.len() as i64, 9).svd(false, true);
    let s = values(&s);
    ensure!(s.len() >= 8 && s[7] > 1e-9 * s[0], "the points do not fix a homography (collinear?)");
    let h = values(&v.select(1, 8));
    let hn: Mat3 = std::array::from_fn(|i| std::array::from_fn(|j| h[i * 3 + j]));
    // H = Ti^-1 Hn Tw.
    let ti_inv = [[1.0 / ti[0][0], 0.0, -ti[0][2] / ti[0][0]], [0.0, 1.0 / ti[1][1], -ti[1][2] / ti[1][1]], [0.0, 0.0, 1.0]];
    let out = mat_mul(&ti_inv, &mat_mul(&hn, &tw));
    let scale = out[2][2];
    ensure!(scale.abs() > 1e-12, "degenerate homography");
    Ok(out.map(|r| r.map(|v| v / scale)))
}

/// The focal length (pixels) that makes the homographies' planes
/// metric (Zhang's constraints with square pixels, no skew and the
/// principal point at `centre`): the least-squares 1/f^2 of
/// h1.w.h2 = 0 and h1.w.h1 = h2.w.h2 over all photos. None when the
/// photos cannot tell (all face the plane straight on).
pub fn focal_from_homographies(hs: &[Mat3], centre: [f64; 2]) -> Option<f64> {
    let (mut aa, mut ab) = (0.0, 0.0);
    for h in hs {
        let shift = [[1.0, 0.0, -centre[0]], [0.0, 1.0, -centre[1]], [0.0, 0.0, 1.0]];
        let g = mat_mul(&shift, h);
        let norm = g.iter().flatten().map(|v| v * v).sum::<f64>().sqrt();
        let g = g.map(|r| r.map(|v| v / norm));
        // With w = diag(x, x, 1), x = 1/f^2: each constraint reads a x + b = 0.
        let constraints = [
            (g[0][0] * g[0][1] + g[1][0] * g[1][1], g[2][0] * g[2][1]),
            (g[0][0].powi(2) + g[1][0].powi(2) - g[0][1].powi(2) - g[1][1].powi(2), g[2][0].powi(2) - g[2][1].powi(2)),
        ];
        for (a, b) in constraints {
            aa += a * a;
            ab += a * b;
        }
    }
    let x = -ab / aa;
    (aa > 1e-18 && x > 0.0).then(|| 1.0 / x.sqrt()).filter(|f| f.is_finite())
}

/// The pose of a camera whose (undistorted) homography from the plane
/// z = 0 is `h`: [r1 r2 t] = K^-1 H scaled, r3 = r1 x r2, made a rotation.
pub fn pose_from_homography(h: &Mat3, k: &Intrinsics) -> Option<Pose> {
    let k_inv = [[1.0 / k.focal, 0.0, -k.centre[0] / k.focal], [0.0, 1.0 / k.focal, -k.centre[1] / k.focal], [0.0, 0.0, 1.0]];
    let m = mat_mul(&k_inv, h);
    let col = |j: usize| [m[0][j], m[1][j], m[2][j]];
    let mut scale = 2.0 / (length(col(0)) + length(col(1)));
    if col(2)[2] * scale < 0.0 {
        scale = -scale; // the plane lies in front of the camera
    }
    let (r1, r2, t) = (col(0).map(|v| v * scale), col(1).map(|v| v * scale), col(2).map(|v| v * scale));
    let r3 = cross(r1, r2);
    let r = nearest_rotation(&[[r1[0], r2[0], r3[0]], [r1[1], r2[1], r3[1]], [r1[2], r2[2], r3[2]]]);
    t.iter().all(|v| v.is_finite()).then_some(Pose { rotation: r, translation: t })
}

/// One photo's tag corners: (frame point mm, pixel).
pub type Correspondences = Vec<([f64; 2], [f64; 2])>;

/// What the joint refinement found.
#[derive(Clone, Debug)]
pub struct Calibration {
    /// Per photo (the principal point is shared by photos of one size).
    pub intrinsics: Vec<Intrinsics>,
    pub poses: Vec<Pose>,
    /// Per photo: root-mean-square reprojection error, pixels.
    pub rms: Vec<f64>,
    /// Whether the distortion terms were fitted (the residuals asked).
    pub distortion: bool,
}

/// Above this overall reprojection RMS (pixels) without distortion, the
/// two radial terms are fitted as well.
pub const DISTORTION_RMS_PX: f64 = 0.35;
/// Prior on the principal point: its standard deviation from the photo's
/// centre, as a fraction of the longer side (phones keep it near).
const CENTRE_PRIOR: f64 = 0.02;
/// Prior standard deviation of k1 and k2 (phone lenses are corrected).
const DISTORTION_PRIOR: f64 = 0.3;
/// The corner noise the priors are weighed against, pixels.
const CORNER_NOISE_PX: f64 = 0.5;

struct Problem<'a> {
    obs: &'a [Correspondences],
    /// Size group of each photo (its own principal point).
    group: Vec<usize>,
    /// The photo-centre of each group, and its longer side.
    group_centre: Vec<([f64; 2], f64)>,
    base: Vec<Mat3>,
    distortion: bool,
    /// The focal length, held (its parameter unused) where the photos'
    /// perspective cannot measure it.
    fixed_focal: Option<f64>,
}

/// Parameters: focal, k1, k2, then (cx, cy) per group, then (rotation
/// vector, translation) per photo, rotations relative to `base`.
impl Problem<'_> {
    fn groups(&self) -> usize {
        self.group_centre.len()
    }

    fn unpack(&self, p: &[f64], photo: usize) -> (Intrinsics, Pose) {
        let g = 3 + 2 * self.group[photo];
        let o = 3 + 2 * self.groups() + 6 * photo;
        // One lens: the focal length scales with the photo's size.
        let scale = self.group_centre[self.group[photo]].1 / self.group_centre[0].1;
        let k = Intrinsics { focal: self.fixed_focal.unwrap_or(p[0]) * scale, centre: [p[g], p[g + 1]], k1: p[1], k2: p[2] };
        let w = [p[o], p[o + 1], p[o + 2]];
        let pose = Pose { rotation: mat_mul(&rotation_from_vector(w), &self.base[photo]), translation: [p[o + 3], p[o + 4], p[o + 5]] };
        (k, pose)
    }

    fn residuals(&self, p: &[f64]) -> Vec<f64> {
        let mut r = Vec::new();
        for (i, photo) in self.obs.iter().enumerate() {
            let (k, pose) = self.unpack(p, i);
            for (w, px) in photo {
                let q = pose.project(&k, [w[0], w[1], 0.0]).unwrap_or([1e6, 1e6]);
                r.push(q[0] - px[0]);
                r.push(q[1] - px[1]);
            }
        }
        for (g, (c, side)) in self.group_centre.iter().enumerate() {
            let weight = CORNER_NOISE_PX / (CENTRE_PRIOR * side);
            r.push((p[3 + 2 * g] - c[0]) * weight);
            r.push((p[4 + 2 * g] - c[1]) * weight);
        }
        let w = CORNER_NOISE_PX / DISTORTION_PRIOR;
        r.push(p[1] * w);
        r.push(p[2] * w);
        r
    }

    fn free(&self, j: usize) -> bool {
        self.distortion || !(j == 1 || j == 2)
    }
}

fn cost(r: &[f64]) -> f64 {
    r.iter().map(|v| v * v).sum()
}

/// Levenberg-Marquardt with a central-difference Jacobian; returns the
/// refined parameters.
fn levenberg_marquardt(problem: &mut Problem, mut p: Vec<f64>, iterations: usize) -> Result<Vec<f64>> {
    let n = p.len();
    let mut lambda = 1e-3;
    let mut r = problem.residuals(&p);
    let mut c = cost(&r);
    for _ in 0..iterations {
        let m = r.len();
        let mut jac = vec![0.0; m * n];
        for j in (0..n).filter(|&j| problem.free(j)) {
            let h = if j == 0 { 1e-4 * p[0] } else { 1e-6 * p[j].abs().max(1e-2) };
            let (mut lo, mut hi) = (p.clone(), p.clone());
            lo[j] -= h;
            hi[j] += h;
            let (rl, rh) = (problem.residuals(&lo), problem.residuals(&hi));
            for i in 0..m {
                jac[i * n + j] = (rh[i] - rl[i]) / (2.0 * h);
            }
        }
        let jt = tensor_of(&jac, m as i64, n as i64);
        let jtj = jt.transpose(0, 1).matmul(&jt);
        let jtr = jt.transpose(0, 1).matmul(&Tensor::from_slice(&r).view([m as i64, 1]));
        let diag = jtj.diagonal(0, 0, 1).clamp_min(1e-12);
        let mut improved = false;
        for _ in 0..10 {
            let a = &jtj + Tensor::diag_embed(&(&diag * lambda), 0, 0, 1);
            let Ok(delta) = Tensor::f_linalg_solve(&a, &(-&jtr), true) else {
                lambda *= 4.0;
                continue;
            };
            let delta = values(&delta);
            let candidate: Vec<f64> = p.iter().zip(&delta).map(|(a, b)| a + b).collect();
            let rc = problem.residuals(&candidate);
            let cc = cost(&rc);
            if cc.is_finite() && cc < c {
                let gain = (c - cc) / c.max(1e-300);
                p = candidate;
                r = rc;
                c = cc;
                lambda = (lambda / 3.0).max(1e-12);
                improved = true;
                if gain < 1e-12 {
                    return Ok(rebase(problem, p));
                }
                break;
            }
            lambda *= 4.0;
        }
        if !improved {
            break;
        }
        p = rebase(problem, p);
    }
    ensure!(c.is_finite(), "the camera refinement diverged");
    Ok(p)
}

/// Folds the rotation increments into the base rotations.
fn rebase(problem: &mut Problem, mut p: Vec<f64>) -> Vec<f64> {
    let groups = problem.groups();
    for (i, base) in problem.base.iter_mut().enumerate() {
        let o = 3 + 2 * groups + 6 * i;
        *base = mat_mul(&rotation_from_vector([p[o], p[o + 1], p[o + 2]]), base);
        p[o..o + 3].fill(0.0);
    }
    p
}

/// Refines one focal length and distortion, a principal point per photo
/// size and a pose per photo from each photo's tag corners. `sizes`: each
/// photo's (width, height), of one aspect ratio: a photo of another size
/// is the same lens scaled (a downscaled copy), its focal length in pixels
/// scaled with its longer side; `focal`: the first guess (pixels of the
/// first photo's size); `poses`: first guesses (from [`pose_from_homography`]).
pub fn calibrate(obs: &[Correspondences], sizes: &[(usize, usize)], focal: f64, poses: &[Pose], fix_focal: bool) -> Result<Calibration> {
    ensure!(obs.len() == sizes.len() && obs.len() == poses.len(), "one size and one pose per photo");
    let mut kinds: Vec<(usize, usize)> = Vec::new();
    let group = sizes
        .iter()
        .map(|s| {
            kinds.iter().position(|k| k == s).unwrap_or_else(|| {
                kinds.push(*s);
                kinds.len() - 1
            })
        })
        .collect();
    let group_centre: Vec<([f64; 2], f64)> = kinds.iter().map(|&(w, h)| ([w as f64 / 2.0, h as f64 / 2.0], w.max(h) as f64)).collect();
    let mut p = vec![focal, 0.0, 0.0];
    for (c, _) in &group_centre {
        p.extend_from_slice(c);
    }
    for pose in poses {
        p.extend_from_slice(&[0.0, 0.0, 0.0]);
        p.extend_from_slice(&pose.translation);
    }
    let mut problem = Problem { obs, group, group_centre, base: poses.iter().map(|p| p.rotation).collect(), distortion: false, fixed_focal: fix_focal.then_some(focal) };
    p = levenberg_marquardt(&mut problem, p, 100)?;
    let points: usize = obs.iter().map(Vec::len).sum();
    let overall = (cost(&problem.residuals(&p)[..2 * points]) / points as f64).sqrt();
    if overall > DISTORTION_RMS_PX {
        problem.distortion = true;
        p = levenberg_marquardt(&mut problem, p, 100)?;
    }
    if !(p[0].is_finite() && p[0] > 0.0) {
        bail!("the camera refinement found no focal length");
    }
    let (mut intrinsics, mut out_poses, mut rms) = (vec![], vec![], vec![]);
    for (i, photo) in obs.iter().enumerate() {
        let (k, pose) = problem.unpack(&p, i);
        let e = photo.iter().map(|(w, px)| pose.project(&k, [w[0], w[1], 0.0]).map_or(1e12, |q| (q[0] - px[0]).powi(2) + (q[1] - px[1]).powi(2))).sum::<f64>();
        rms.push((e / photo.len().max(1) as f64).sqrt());
        intrinsics.push(k);
        out_poses.push(pose);
    }
    Ok(Calibration { intrinsics, poses: out_poses, rms, distortion: problem.distortion })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid() -> Vec<[f64; 2]> {
        (0..5).flat_map(|i| (0..5).map(move |j| [-60.0 + 30.0 * i as f64, -60.0 + 30.0 * j as f64])).collect()
    }

    #[test]
    fn look_at_projects_the_target_to_the_centre_and_plane_point_inverts_project() {
        let k = Intrinsics { focal: 1000.0, centre: [800.0, 600.0], k1: -0.05, k2: 0.01 };
        let pose = Pose::look_at([40.0, -30.0, 200.0], [0.0, 0.0, 0.0], [0.0, 1.0, 0.0]);
        let c = pose.project(&k, [0.0, 0.0, 0.0]).unwrap();
        assert!((c[0] - 800.0).abs() < 1e-9 && (c[1] - 600.0).abs() < 1e-9, "{c:?}");
        let centre = pose.centre();
        assert!((centre[0] - 40.0).abs() < 1e-9 && (centre[2] - 200.0).abs() < 1e-9);
        for w in grid() {
            let px = pose.project(&k, [w[0], w[1], 0.0]).unwrap();
            let back = pose.plane_point(&k, px).unwrap();
            assert!((back[0] - w[0]).abs() < 1e-7 && (back[1] - w[1]).abs() < 1e-7, "{w:?} -> {back:?}");
        }
        // Up the page (+y) is up the image (-rows) for a camera looking down with up = +y.
        let a = pose.project(&k, [0.0, 10.0, 0.0]).unwrap();
        assert!(a[1] < c[1]);
    }

    #[test]
    fn rodrigues_turns_by_its_angle() {
        let r = rotation_from_vector([0.0, 0.0, std::f64::consts::FRAC_PI_2]);
        let v = mat_vec(&r, [1.0, 0.0, 0.0]);
        assert!((v[0]).abs() < 1e-12 && (v[1] - 1.0).abs() < 1e-12);
        let id = rotation_from_vector([0.0; 3]);
        assert!((rotation_angle_deg(&r, &id) - 90.0).abs() < 1e-9);
    }

    #[test]
    fn homography_pose_and_focal_come_back_from_exact_views() {
        let k = Intrinsics::centred(1200.0, 1600, 1200);
        let eyes = [[0.0, 0.0, 250.0], [90.0, -70.0, 230.0], [-80.0, 90.0, 240.0]];
        let mut hs = vec![];
        for (n, eye) in eyes.iter().enumerate() {
            let truth = Pose::look_at(*eye, [3.0, -2.0, 0.0], [0.3 * n as f64, 1.0, 0.0]);
            let pairs: Vec<_> = grid().into_iter().map(|w| (w, truth.project(&k, [w[0], w[1], 0.0]).unwrap())).collect();
            let h = homography(&pairs).unwrap();
            hs.push(h);
            let pose = pose_from_homography(&h, &k).unwrap();
            let c = pose.centre();
            assert!(length(sub(c, *eye)) < 1e-6, "{c:?} vs {eye:?}");
            assert!(rotation_angle_deg(&pose.rotation, &truth.rotation) < 1e-4);
        }
        // The tilted photos fix the focal length.
        let f = focal_from_homographies(&hs, k.centre).unwrap();
        assert!((f - 1200.0).abs() < 1e-4, "{f}");
    }

    #[test]
    fn calibration_recovers_focal_distortion_and_poses_from_noisy_corners() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let truth_k = Intrinsics { focal: 1400.0, centre: [812.0, 590.0], k1: -0.08, k2: 0.02 };
        let eyes = [[0.0, 0.0, 260.0], [90.0, -70.0, 230.0], [-80.0, 90.0, 240.0], [85.0, 80.0, 220.0]];
        let mut obs = vec![];
        let mut truths = vec![];
        for (n, eye) in eyes.iter().enumerate() {
            let truth = Pose::look_at(*eye, [0.0, 0.0, 0.0], [0.2 * n as f64, 1.0, 0.0]);
            let pairs: Correspondences = grid()
                .into_iter()
                .map(|w| {
                    let p = truth.project(&truth_k, [w[0], w[1], 0.0]).unwrap();
                    (w, [p[0] + rng.random_range(-0.3..0.3), p[1] + rng.random_range(-0.3..0.3)])
                })
                .collect();
            obs.push(pairs);
            truths.push(truth);
        }
        // First guesses as `flashmat capture` makes them: a 10% wrong focal, no distortion.
        let k0 = Intrinsics::centred(1540.0, 1600, 1200);
        let poses: Vec<Pose> = obs.iter().map(|o| pose_from_homography(&homography(o).unwrap(), &k0).unwrap()).collect();
        let cal = calibrate(&obs, &vec![(1600, 1200); 4], 1540.0, &poses, false).unwrap();
        assert!(cal.distortion, "a k1 of -0.08 shows in the residuals");
        assert!((cal.intrinsics[0].focal - 1400.0).abs() < 10.0, "{:?}", cal.intrinsics[0]);
        for (pose, truth) in cal.poses.iter().zip(&truths) {
            assert!(length(sub(pose.centre(), truth.centre())) < 1.5, "{:?} vs {:?}", pose.centre(), truth.centre());
            assert!(rotation_angle_deg(&pose.rotation, &truth.rotation) < 0.3);
        }
        assert!(cal.rms.iter().all(|&r| r < 0.3), "{:?}", cal.rms);
    }
}
