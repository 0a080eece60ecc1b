//! Memory-bounded inference: M_est runs on the whole photo when its
//! activations fit in `--max-memory`, else layer by layer over tiles
//! (`model::m_est::FoldedMEst::forward_layerwise`: exact up to float
//! rounding, because every layer's instance norm takes the statistics of
//! its whole input; no seams, no blending needed); relighting streams row
//! bands (M_render is per pixel, so bands are exact).
//!
//! On a GPU the plan takes `--max-memory` as the card's budget too; it is
//! not read from the card's free memory: tch exposes no `cudaMemGetInfo`
//! (PyTorch's `torch.cuda.mem_get_info`), and reaching it through the CUDA
//! runtime by hand could not be tested without a GPU. Running out anyway is
//! one error line that says to lower `--max-memory` (`src/main.rs`).

use crate::model::ModelConfig;
use anyhow::{bail, ensure, Result};

/// Default `--max-memory`: 8 GiB.
pub const DEFAULT_MAX_MEMORY: u64 = 8 << 30;

/// Smallest accepted `--max-memory`: 64 MiB.
pub const MIN_MAX_MEMORY: u64 = 64 << 20;

/// Largest tile core of the layer-wise forward (larger tiles only cost
/// memory; 512 is already few calls per layer).
pub const MAX_TILE_CORE: i64 = 512;

/// Smallest tile core worth running.
pub const MIN_TILE_CORE: i64 = 64;

/// Bytes per pixel beside M_est's activations, either way: the linear
/// photo and its copies (3 x 3), the input (4), the neural map (C), f32.
fn fixed_bytes_per_pixel(cfg: &ModelConfig) -> f64 {
    4.0 * (9.0 + 4.0 + cfg.neural_channels as f64)
}

/// Peak bytes per pixel of the whole M_est forward (folded, no autograd),
/// f32: the skip tensors (W + 2W/4 + 4W/16 + 8W/64 = 1.875 W) plus the
/// widest full-resolution layer's working set (decoder block 1 reads 3W
/// channels: padded input, merged gate/inception convs of 2.5 x its
/// outputs, the instance-normalised copy, the features; about 24 W) and the
/// head's C outputs. Checked against measured peaks (README, `flashmat
/// estimate` prints its peak).
pub fn est_bytes_per_pixel(cfg: &ModelConfig) -> f64 {
    4.0 * (26.0 * cfg.est_width as f64 + cfg.neural_channels as f64)
}

/// Bytes per pixel of the layer-wise forward besides one tile: the skip
/// tensors (1.875 W), and at the widest step (decoder block 1) the
/// previous and the concatenated input (2W + 3W), the block's two
/// outputs and its identity path (3W), and the head's C outputs.
pub fn layerwise_bytes_per_pixel(cfg: &ModelConfig) -> f64 {
    4.0 * (10.0 * cfg.est_width as f64 + cfg.neural_channels as f64)
}

/// How M_est will run on an `h x w` input.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum EstPlan {
    Whole,
    /// Layer by layer over tiles of this core side (a multiple of 8).
    Tiled(i64),
}

/// How much more than [`est_bytes_per_pixel`] the whole forward's peak may
/// reach: `flashmat` keeps freed memory in the heap for reuse (2x faster on
/// large maps, `src/main.rs`), and the heap then fragments between the
/// layers' differently sized tensors. Measured peaks against the estimate
/// (compact, whole): 1024x1024 1.07-1.1x, 1536x1024 1.27-1.43x; the
/// layer-wise forward's peak did not change (2048x2048: 3.80 GiB).
pub const WHOLE_HEAP_SLACK: f64 = 1.5;

/// Whole when the forward fits in `max_memory` (with
/// [`WHOLE_HEAP_SLACK`]); else layer-wise tiles
/// with the largest core (multiple of 8, up to [`MAX_TILE_CORE`]) whose
/// tile working set fits beside the layer-wise tensors. Errors with the
/// memory needed when even [`MIN_TILE_CORE`] does not fit.
pub fn plan_estimate(cfg: &ModelConfig, h: usize, w: usize, max_memory: u64) -> Result<EstPlan> {
    let px = (h * w) as f64;
    let fixed = fixed_bytes_per_pixel(cfg) * px;
    let budget = max_memory as f64;
    if fixed + WHOLE_HEAP_SLACK * est_bytes_per_pixel(cfg) * px <= budget {
        return Ok(EstPlan::Whole);
    }
    let left = budget - fixed - layerwise_bytes_per_pixel(cfg) * px;
    let tile_side = if left > 0.0 { (left / est_bytes_per_pixel(cfg)).sqrt() as i64 } else { 0 };
    let core = ((tile_side - 2 * crate::model::m_est::LAYER_HALO) / 8 * 8).min(MAX_TILE_CORE);
    if core < MIN_TILE_CORE {
        let need = fixed + layerwise_bytes_per_pixel(cfg) * px + est_bytes_per_pixel(cfg) * ((MIN_TILE_CORE + 16) as f64).powi(2);
        bail!(
            "--max-memory {:.2} GiB is too small for a {w}x{h} estimate: it needs at least {:.2} GiB; lower --size or raise --max-memory",
            budget / (1u64 << 30) as f64,
            need / (1u64 << 30) as f64
        );
    }
    Ok(EstPlan::Tiled(core))
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
        // compact (W = 16, C = 64): whole (26 x 16 + 64) x 4 = 1920 B/px, layer-wise
        // (10 x 16 + 64) x 4 = 896 B/px, fixed (13 + 64) x 4 = 308 B/px.
        assert_eq!((est_bytes_per_pixel(&cfg), layerwise_bytes_per_pixel(&cfg)), (1920.0, 896.0));
        // 1024^2: 1.05 M px x (308 + 1.5 x 1920) B = 3.11 GiB: whole.
        assert_eq!(plan_estimate(&cfg, 1024, 1024, DEFAULT_MAX_MEMORY).unwrap(), EstPlan::Whole);
        // 1536 x 2048: 3.15 M px x 3188 B = 9.35 GiB > 8 GiB with the heap's
        // slack (6.53 GiB without): layer-wise.
        assert!(matches!(plan_estimate(&cfg, 1536, 2048, DEFAULT_MAX_MEMORY).unwrap(), EstPlan::Tiled(_)));
        // 2048^2: 4.19 M px x 3188 B = 12.4 GiB > 8 GiB: layer-wise, 4.19 M px x 1204 B
        // = 4.70 GiB, tiles of up to 512 in the rest.
        assert_eq!(plan_estimate(&cfg, 2048, 2048, DEFAULT_MAX_MEMORY).unwrap(), EstPlan::Tiled(512));
        // 2048 x 3072 in 8 GiB: 7.05 GiB layer-wise; 0.95 GiB / 1920 B -> 727 px tiles -> 512.
        assert_eq!(plan_estimate(&cfg, 2048, 3072, DEFAULT_MAX_MEMORY).unwrap(), EstPlan::Tiled(512));
        // 2048^2 in 4.8 GiB: 0.097 GiB left / 1920 B -> side 232 -> core 232 - 16 -> 216.
        assert_eq!(plan_estimate(&cfg, 2048, 2048, (4.8 * (1u64 << 30) as f64) as u64).unwrap(), EstPlan::Tiled(216));
        let e = plan_estimate(&cfg, 2048, 2048, 1 << 30).unwrap_err().to_string();
        assert!(e.contains("too small") && e.contains("needs at least 4.7") && e.contains("--max-memory"), "{e}");
        assert!(render_band_rows(&cfg, 2048, 1) >= 8);
    }
}
