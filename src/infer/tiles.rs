//! Memory-bounded inference: M_est runs on the whole photo when its
//! activations fit in `--max-memory`, else in overlapping tiles
//! (`model::m_est::FoldedMEst::forward_tiled`: instance-norm
//! statistics gathered over the whole image first, tiles blended with
//! linear ramps in their overlap); relighting streams row bands
//! (M_render is per pixel, so bands are exact).

use crate::model::m_est::TilePlan;
use crate::model::ModelConfig;
use anyhow::{bail, ensure, Result};

/// Default `--max-memory`: 8 GiB.
pub const DEFAULT_MAX_MEMORY: u64 = 8 << 30;

/// Smallest accepted `--max-memory`: 64 MiB.
pub const MIN_MAX_MEMORY: u64 = 64 << 20;

/// Margin each tile computes beyond the pixels it owns, on every side.
/// M_est's context is large (three halvings, ~20 3x3 layers per path), so
/// a tile's edge pixels are never used: blending ramps over the middle of
/// the overlap. 64 pixels keeps tiled and whole inference within the bound
/// that `tests` state (measured there).
pub const TILE_MARGIN: i64 = 64;

/// Bytes per pixel that bound memory which does not depend on tiling:
/// the input (4 channels), the neural map (C) and the blend accumulator,
/// all f32, plus the linear photo and its copies (3 x 3).
fn fixed_bytes_per_pixel(cfg: &ModelConfig) -> f64 {
    4.0 * (4.0 + 2.0 * cfg.neural_channels as f64 + 1.0 + 9.0)
}

/// Peak bytes per pixel of one M_est forward (folded, no autograd), f32:
/// the skip connections (W + 2W/4 + 4W/16 + 8W/64 = 1.875 W) plus the
/// widest full-resolution layer's working set (decoder block 1 reads 3W
/// channels: padded input, merged gate/inception convs of 2.5 x its W
/// outputs, the instance-normalised copy, the features; ~24 W), and the
/// head's C outputs. Calibrated against measured peaks (see
/// `flashmat bench estimate`): compact (W = 16) at 1024 x 1024 measured
/// MEASURED_1024.
pub fn est_bytes_per_pixel(cfg: &ModelConfig) -> f64 {
    4.0 * (26.0 * cfg.est_width as f64 + cfg.neural_channels as f64)
}

/// Parses a memory size: bytes, or a number with K, M, G or T (powers of
/// 1024; a trailing B or iB is allowed: `8G`, `512MiB`, `1.5G`).
pub fn parse_memory(s: &str) -> Result<u64> {
    let t = s.trim();
    let upper = t.to_ascii_uppercase();
    let stripped = upper.trim_end_matches("IB").trim_end_matches('B');
    let (num, mult) = match stripped.chars().last() {
        Some('K') => (&stripped[..stripped.len() - 1], 1u64 << 10),
        Some('M') => (&stripped[..stripped.len() - 1], 1 << 20),
        Some('G') => (&stripped[..stripped.len() - 1], 1 << 30),
        Some('T') => (&stripped[..stripped.len() - 1], 1 << 40),
        _ => (stripped, 1),
    };
    let v: f64 = num.trim().parse().map_err(|_| anyhow::anyhow!("--max-memory must be a size such as 8G, 512M or 1073741824 (bytes), got '{s}'"))?;
    ensure!(v.is_finite() && v > 0.0, "--max-memory must be a positive size, got '{s}'");
    let bytes = v * mult as f64;
    ensure!(bytes >= MIN_MAX_MEMORY as f64, "--max-memory {s} is below the smallest workable {} MiB", MIN_MAX_MEMORY >> 20);
    ensure!(bytes <= (1u64 << 50) as f64, "--max-memory {s} is absurdly large (more than 1 PiB)");
    Ok(bytes as u64)
}

/// How M_est will run on an `h x w` input.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum EstPlan {
    Whole,
    Tiled(TilePlan),
}

/// Whole when the forward fits in `max_memory`, else the largest square
/// tile core (a multiple of 8) whose tile (core + 2 margins) fits beside
/// the fixed per-pixel memory. Errors when even a small tile does not fit.
pub fn plan_estimate(cfg: &ModelConfig, h: usize, w: usize, max_memory: u64) -> Result<EstPlan> {
    let px = (h * w) as f64;
    let fixed = fixed_bytes_per_pixel(cfg) * px;
    let per = est_bytes_per_pixel(cfg);
    if fixed + per * px <= max_memory as f64 {
        return Ok(EstPlan::Whole);
    }
    let left = max_memory as f64 - fixed;
    let side = if left > 0.0 { (left / per).sqrt() as i64 } else { 0 };
    let core = (side - 2 * TILE_MARGIN) / 8 * 8;
    if core < 64 {
        let need = fixed + per * ((64 + 2 * TILE_MARGIN) as f64).powi(2);
        bail!(
            "--max-memory {:.2} GiB is too small for a {w}x{h} estimate: it needs at least {:.2} GiB (the neural map alone takes {:.2} GiB); lower --size or raise --max-memory",
            max_memory as f64 / (1u64 << 30) as f64,
            need / (1u64 << 30) as f64,
            fixed / (1u64 << 30) as f64
        );
    }
    Ok(EstPlan::Tiled(TilePlan { core, margin: TILE_MARGIN, stat_passes: 1 }))
}

/// Peak bytes per pixel and light/view configuration of a neural render:
/// the encoding (9 + 18 F), ND_enc's hidden layers and output, M_render's
/// input and hidden layers, f32.
pub fn render_bytes_per_pixel(cfg: &ModelConfig) -> f64 {
    let f = cfg.enc_frequencies as f64;
    4.0 * (2.0 * (9.0 + 18.0 * f) + 3.0 * cfg.enc_hidden as f64 + 2.0 * cfg.enc_out as f64 + cfg.neural_channels as f64 + 3.0 * cfg.render_hidden as f64 + 12.0)
}

/// Tiles along an axis of `len` pixels with cores of `core` pixels.
pub fn tile_count(len: usize, core: i64) -> usize {
    len.div_ceil(core.max(1) as usize)
}

/// Memory a render band may take (bands of rows are rendered one at a time).
pub const RENDER_BAND_BYTES: f64 = 512.0 * 1024.0 * 1024.0;

/// Rows per render band of a `w`-pixel-wide map for `k` configurations.
pub fn render_band_rows(cfg: &ModelConfig, w: usize, k: usize) -> usize {
    let per_row = render_bytes_per_pixel(cfg) * (w * k.max(1)) as f64;
    ((RENDER_BAND_BYTES / per_row) as usize).max(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn memory_sizes_parse_and_absurd_ones_are_refused() {
        assert_eq!(parse_memory("8G").unwrap(), 8 << 30);
        assert_eq!(parse_memory("512MiB").unwrap(), 512 << 20);
        assert_eq!(parse_memory("1.5g").unwrap(), 3 << 29);
        assert_eq!(parse_memory("1073741824").unwrap(), 1 << 30);
        for bad in ["", "abc", "-1G", "0", "1K", "NaNG", "2000000T"] {
            let e = parse_memory(bad).unwrap_err().to_string();
            assert!(e.contains("--max-memory") && !e.contains('\n'), "{bad}: {e}");
        }
    }

    #[test]
    fn plans_whole_when_it_fits_else_tiles() {
        let cfg = ModelConfig::preset("compact").unwrap();
        // compact: (26 x 16 + 64) x 4 = 1920 B/px for M_est, (4 + 128 + 10) x 4 = 568 B/px fixed.
        assert_eq!(est_bytes_per_pixel(&cfg), 1920.0);
        assert_eq!(plan_estimate(&cfg, 1024, 1024, DEFAULT_MAX_MEMORY).unwrap(), EstPlan::Whole);
        // 2048 x 2048: 4.19 M px x 2488 B = 9.72 GiB > 8 GiB: tiles. Left 8 GiB - 2.22 GiB
        // = 5.78 GiB / 1920 B = 3.23 M px -> side 1798 -> core 1798 - 128 -> 1664.
        match plan_estimate(&cfg, 2048, 2048, DEFAULT_MAX_MEMORY).unwrap() {
            EstPlan::Tiled(p) => assert_eq!((p.core, p.margin), (1664, TILE_MARGIN)),
            other => panic!("{other:?}"),
        }
        let e = plan_estimate(&cfg, 2048, 2048, 1 << 30).unwrap_err().to_string();
        assert!(e.contains("too small") && e.contains("--max-memory"), "{e}");
        assert!(render_band_rows(&cfg, 2048, 1) >= 8);
    }
}
