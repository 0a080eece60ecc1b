//! `flashmat show`: one picture summarising a neural material: the input
//! photo, two views of the neural map (per-pixel norm; first three
//! principal components as RGB), the identity render and four relit views.

use super::{orbit_configs, overhead_camera, NeuralMaterial, ORBIT_HEIGHT, ORBIT_RADIUS};
use crate::image::Image;
use anyhow::{ensure, Result};
use tch::{Kind, Tensor};

/// Gap between grid cells in pixels.
pub const GRID_GAP: usize = 4;

/// Grid columns: row 1 = photo, map norm, map PCA, identity render;
/// row 2 = four relit views.
pub const GRID_COLUMNS: usize = 4;

/// Principal components of the per-pixel parameter vectors.
pub struct Pca {
    /// Unit principal axes as columns `[C, k]`, by decreasing variance.
    /// Each axis's sign makes its largest-magnitude entry positive.
    pub axes: Tensor,
    /// Variance along each axis `[k]`.
    pub variances: Tensor,
    /// Centred parameters projected on the axes `[k, H, W]`.
    pub projections: Tensor,
}

/// Top-`k` principal components of a neural map, from the C x C
/// covariance of its pixels (eigendecomposition in double precision).
/// map: `[C, H, W]` with k <= C.
pub fn principal_components(map: &Tensor, k: i64) -> Result<Pca> {
    let s = map.size();
    ensure!(s.len() == 3, "neural map must be [C, H, W], got {s:?}");
    let (c, h, w) = (s[0], s[1], s[2]);
    ensure!((1..=c).contains(&k), "cannot take {k} principal components of {c} channels");
    let x = map.to_kind(Kind::Double).reshape([c, h * w]).transpose(0, 1); // [HW, C]
    let xc = &x - x.mean_dim([0i64].as_slice(), true, Kind::Double);
    let cov = xc.transpose(0, 1).matmul(&xc) / ((h * w - 1).max(1) as f64); // [C, C]
    let (evals, evecs) = cov.linalg_eigh("L"); // ascending
    let idx = Tensor::arange_start_step(c - 1, c - 1 - k, -1, (Kind::Int64, map.device()));
    let mut axes = evecs.index_select(1, &idx); // [C, k]
    let variances = evals.index_select(0, &idx).clamp_min(0.0);
    // Eigenvectors have arbitrary signs; fix one so pictures are stable.
    let pivot = axes.abs().argmax(0, true); // [1, k]
    let sign = axes.gather(0, &pivot, false).sign();
    axes *= sign;
    let projections = xc.matmul(&axes).transpose(0, 1).reshape([k, h, w]);
    Ok(Pca { axes, variances, projections })
}

/// First three principal components as RGB `[3, H, W]` in [0, 1]: each
/// component maps +-3 standard deviations to [0, 1] (grey = the mean).
/// Maps with fewer than 3 channels leave the missing colours at 0.5.
pub fn pca_picture(map: &Tensor) -> Result<Image> {
    let s = map.size();
    let k = s[0].min(3);
    let pca = principal_components(map, k)?;
    let std = pca.variances.sqrt().clamp_min(1e-12).view([k, 1, 1]);
    let mut rgb = (pca.projections / (std * 6.0) + 0.5).clamp(0.0, 1.0);
    if k < 3 {
        rgb = Tensor::cat(&[rgb, Tensor::full([3 - k, s[1], s[2]], 0.5, (Kind::Double, map.device()))], 0);
    }
    Image::from_tensor(&rgb)
}

/// Per-pixel L2 norm of the parameters as grey `[1, H, W]`, divided by its
/// 99th percentile (so a few outliers do not darken the picture).
pub fn norm_picture(map: &Tensor) -> Result<Image> {
    let norm = map.to_kind(Kind::Float).square().sum_dim_intlist([0i64].as_slice(), true, Kind::Float).sqrt(); // [1, H, W]
    let mut values: Vec<f32> = Vec::try_from(norm.flatten(0, -1).to_device(tch::Device::Cpu))?;
    values.sort_by(f32::total_cmp);
    let p99 = values[((values.len() - 1) as f64 * 0.99).round() as usize].max(1e-12);
    Image::from_tensor(&(norm / p99 as f64).clamp(0.0, 1.0))
}

/// The summary grid (display-encoded `[3, h, w]`): row 1 = input photo,
/// neural-map norm, neural-map PCA, identity render; row 2 = the light
/// circling the material (as in `relight --orbit`) at four azimuths
/// (+x, +y, -x, -y), camera overhead. Cells are the material's resolution,
/// with [`GRID_GAP`] pixels between them.
pub fn show_grid(material: &NeuralMaterial) -> Result<Image> {
    let disp = |im: &Image| im.to_display();
    let identity = material.render_image(&NeuralMaterial::identity_config())?;
    let row1 = vec![
        disp(&material.input_image()?),
        norm_picture(&material.neural_map)?,
        pca_picture(&material.neural_map)?,
        disp(&identity),
    ];
    let relit = material.render(&orbit_configs(4, ORBIT_RADIUS, ORBIT_HEIGHT, overhead_camera()))?;
    let row2 = (0..4).map(|i| Image::from_tensor(&relit.get(i)).map(|im| disp(&im))).collect::<Result<Vec<_>>>()?;
    crate::viz::grid(&[row1, row2], GRID_GAP)
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::Device;

    #[test]
    fn pca_recovers_planted_axes() {
        // Pixels = mean + 3 a u + 2 b v + 1 c w + small noise, with
        // orthonormal u, v, w in 8 channels and independent unit-variance
        // a, b, c: the principal axes are u, v, w with variances 9, 4, 1.
        tch::manual_seed(0);
        let (c, n) = (8i64, 64i64);
        let opts = (Kind::Double, Device::Cpu);
        let (q, _) = Tensor::linalg_qr(&Tensor::randn([c, c], opts), "reduced");
        let coeffs = Tensor::randn([3, n * n], opts);
        let coeffs = (&coeffs - coeffs.mean_dim([1i64].as_slice(), true, Kind::Double)) / coeffs.std_dim([1i64].as_slice(), true, true);
        let scales = Tensor::from_slice(&[3.0f64, 2.0, 1.0]).view([3, 1]);
        let pixels = q.narrow(1, 0, 3).matmul(&(coeffs * scales)) + 5.0 + Tensor::randn([c, n * n], opts) * 0.01;
        let pca = principal_components(&pixels.view([c, n, n]).to_kind(Kind::Float), 3).unwrap();
        for i in 0..3 {
            let cos = pca.axes.select(1, i).dot(&q.select(1, i)).abs().double_value(&[]);
            assert!(cos > 0.999, "axis {i}: |cos| = {cos}");
        }
        let v: Vec<f64> = Vec::try_from(pca.variances).unwrap();
        assert!((v[0] - 9.0).abs() < 0.1 && (v[1] - 4.0).abs() < 0.1 && (v[2] - 1.0).abs() < 0.05, "{v:?}");
        assert_eq!(pca.projections.size(), [3, n, n]);
        let pic = pca_picture(&pixels.view([c, n, n])).unwrap();
        assert_eq!((pic.channels, pic.height, pic.width), (3, 64, 64));
        assert!(pic.data.iter().all(|v| (0.0..=1.0).contains(v)));
        // Centred: the mean pixel maps to mid-grey.
        assert!((pic.mean() - 0.5).abs() < 0.02);
    }

    #[test]
    fn norm_picture_and_few_channels() {
        let map = Tensor::from_slice(&[3.0f32, 0.0, 0.0, 0.0, 4.0, 0.0, 1.0, 0.0]).view([2, 2, 2]);
        let im = norm_picture(&map).unwrap();
        assert_eq!(im.channels, 1);
        assert!((im.get(0, 0, 0) - 1.0).abs() < 1e-6 && im.get(0, 0, 1) == 0.0);
        let pic = pca_picture(&map).unwrap();
        assert_eq!(pic.channels, 3);
        assert!(pic.plane(2).iter().all(|&v| v == 0.5));
    }

    #[test]
    fn grid_layout() {
        let m = crate::infer::nmat::tests::random_material(5, 16);
        let g = show_grid(&m).unwrap();
        assert_eq!((g.channels, g.height, g.width), (3, 2 * (16 + GRID_GAP) + GRID_GAP, GRID_COLUMNS * (16 + GRID_GAP) + GRID_GAP));
    }
}
