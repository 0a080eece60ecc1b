//! Upper bounds on every size that decides how much memory is allocated:
//! image dimensions from file headers, resolution and count options, model
//! widths. Each is checked before anything of that size is allocated, so
//! an absurd option or a hostile header is one clear error line instead of
//! an abort on a failed allocation.
//!
//! The defaults leave room for every recipe of the project (the GPU
//! campaign included); each can be raised with its environment variable,
//! which the error message names.

use anyhow::{bail, Result};

/// One named limit with its default and the environment variable that
/// replaces it.
#[derive(Clone, Copy, Debug)]
pub struct Limit {
    /// Environment variable holding a replacement value (a positive integer).
    pub env: &'static str,
    pub default: u64,
    /// Unit of the value in messages ("pixels", "materials", ...).
    pub unit: &'static str,
}

impl Limit {
    /// The limit in force: the environment variable's value when it holds a
    /// positive integer (underscores allowed), else the default.
    pub fn get(&self) -> u64 {
        std::env::var(self.env).ok().and_then(|v| v.trim().replace('_', "").parse().ok()).filter(|&v| v > 0).unwrap_or(self.default)
    }

    /// Errors when `value` exceeds the limit: one line naming `what`, the
    /// limit and how to raise it.
    pub fn check(&self, what: impl std::fmt::Display, value: u64) -> Result<()> {
        let limit = self.get();
        if value > limit {
            bail!("{what} is {value} {}, above the limit of {limit} (set {}=N to raise it)", self.unit, self.env);
        }
        Ok(())
    }

    /// [`Limit::check`] of a product, saturating (no overflow for absurd factors).
    pub fn check_product(&self, what: impl std::fmt::Display, factors: &[u64]) -> Result<()> {
        self.check(what, factors.iter().fold(1u64, |a, &b| a.saturating_mul(b)))
    }
}

/// Pixels of a decoded image file (width x height): 200 megapixels, the
/// largest phone sensors. Decoding and preparing a photo takes about 36
/// bytes per pixel (7 GB at the limit).
pub const IMAGE_PIXELS: Limit = Limit { env: "FLASHMAT_MAX_IMAGE_PIXELS", default: 200_000_000, unit: "pixels" };

/// Bytes of any input file read whole (photos, models, materials,
/// checkpoints): 4 GiB.
pub const FILE_BYTES: Limit = Limit { env: "FLASHMAT_MAX_FILE_BYTES", default: 4 << 30, unit: "bytes" };

/// Side of M_est's input (`--size` of estimate, relight, show, eval): the
/// compact model takes 2.3 GB at 1024 and grows with the square.
pub const MODEL_SIZE: Limit = Limit { env: "FLASHMAT_MAX_SIZE", default: 2048, unit: "pixels" };

/// Side of a generated or rendered material (`--size` of render and
/// svbrdf): 10 float maps, 670 MB at 4096, plus the render.
pub const MATERIAL_SIZE: Limit = Limit { env: "FLASHMAT_MAX_MATERIAL_SIZE", default: 4096, unit: "pixels" };

/// Training crop side (`--crop`; paper: 192 and 256).
pub const TRAIN_CROP: Limit = Limit { env: "FLASHMAT_MAX_CROP", default: 1024, unit: "pixels" };

/// Rendered pixels of one training step: materials x (outputs + 1) x
/// crop^2 (paper: 8 x 5 x 256^2 = 2.6 M; the GPU recipe 8 x 9 x 128^2 =
/// 1.2 M). Activations of every network scale with it.
pub const STEP_PIXELS: Limit = Limit { env: "FLASHMAT_MAX_STEP_PIXELS", default: 1 << 26, unit: "pixels" };

/// Pixels held by a procedural material bank (`--bank` x material side^2,
/// 40 bytes each: 21 GB at the limit; the GPU recipe's 4000 x 256^2 is
/// about half of it).
pub const BANK_PIXELS: Limit = Limit { env: "FLASHMAT_MAX_BANK_PIXELS", default: 1 << 29, unit: "pixels" };

/// Items of a count option that are all held in memory (`nmat-rows
/// --count`, `svbrdf generate|preview --count`, `eval --configs`, ...).
pub const COUNT: Limit = Limit { env: "FLASHMAT_MAX_COUNT", default: 100_000, unit: "items" };

/// M_est's base width W (parameters grow with W^2: 84 M at the paper's 64,
/// 1.3 G at 256).
pub const EST_WIDTH: Limit = Limit { env: "FLASHMAT_MAX_EST_WIDTH", default: 256, unit: "channels" };

/// Every other layer width of a model configuration (the paper's widest
/// is ND_enc's 594).
pub const LAYER_WIDTH: Limit = Limit { env: "FLASHMAT_MAX_LAYER_WIDTH", default: 4096, unit: "channels" };

/// libtorch threads (`--threads`).
pub const MAX_THREADS: i64 = 1024;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn message_names_the_limit_and_its_variable() {
        let l = Limit { env: "FLASHMAT_TEST_LIMIT_UNSET", default: 10, unit: "pixels" };
        assert!(l.check("--size", 10).is_ok());
        let e = l.check("--size", 11).unwrap_err().to_string();
        assert_eq!(e, "--size is 11 pixels, above the limit of 10 (set FLASHMAT_TEST_LIMIT_UNSET=N to raise it)");
        assert!(l.check_product("the step", &[u64::MAX, 3]).is_err());
    }
}
