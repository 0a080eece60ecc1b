//! Network sizes: the paper's, a CPU-trainable `compact` one and a `tiny`
//! one for tests. All presets share the same architecture; only widths change.

use anyhow::{bail, ensure, Context, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Sizes of M_est, ND_enc, M_render and the discriminator.
///
/// TOML files may give any subset of the fields; missing ones take the
/// `paper` values. `name` only labels the configuration (it is part of
/// [`ModelConfig::model_id`]).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ModelConfig {
    /// Preset name or a user label for a custom configuration.
    pub name: String,
    /// M_est base width W (stages W, 2W, 4W, 8W). Must be even (HA layers
    /// split their output in halves).
    pub est_width: i64,
    /// Neural parameters per pixel (M_est output channels).
    pub neural_channels: i64,
    /// Sinusoid frequencies per direction component (k = 0..n-1).
    pub enc_frequencies: i64,
    /// ND_enc hidden width (two hidden layers).
    pub enc_hidden: i64,
    /// ND_enc output width (the compressed direction code).
    pub enc_out: i64,
    /// M_render width of its five 128-wide layers.
    pub render_hidden: i64,
    /// M_render width of its penultimate (64-wide) layer.
    pub render_narrow: i64,
    /// Discriminator width of its first layer (doubles three times).
    pub disc_width: i64,
    /// ND_enc also reads [`crate::model::nd_enc::half_angle_feature`] of
    /// each direction pair: -ln(1 - h_z + eps) / ln(1 / eps), the half
    /// angle on a log scale (issue 48). A GGX lobe of width alpha is a
    /// spike in h but, in log D, a soft bend at ln(alpha^2) of ln(1 - h_z):
    /// a shape an MLP of LeakyReLUs draws with a few units. Not the paper's.
    /// Written only when set, so files without it read as before everywhere.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub half_angle_feature: bool,
    /// M_est writes the 10 GGX values of each pixel (kd, ks, roughness,
    /// normal) and a frozen per-pixel encoder of a teacher
    /// ([`crate::model::ggx_codes`]) turns them, projected onto valid GGX
    /// values, into the neural map: every code M_est can write is one a
    /// GGX pixel has (issue 48). The renderer
    /// and the neural map are the base preset's; only M_est's head differs.
    /// Not the paper's. Written only when set.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub ggx_codes: bool,
}

impl Default for ModelConfig {
    fn default() -> Self {
        Self::paper()
    }
}

/// Names accepted by [`ModelConfig::preset`].
pub const PRESETS: [&str; 7] = ["paper", "compact", "compact-f8", "compact-h", "compact-f8h", "compact-g", "tiny"];

impl ModelConfig {
    /// The sizes of the paper and the authors' code: M_est 84,008,960
    /// parameters, ND_enc 297 -> 594 -> 594 -> 32, M_render 96 -> 128 x5 ->
    /// 64 -> 3. About 1.04 TFLOP for one 256x256 M_est forward.
    pub fn paper() -> Self {
        Self {
            name: "paper".into(),
            est_width: 64,
            neural_channels: 64,
            enc_frequencies: 16,
            enc_hidden: 594,
            enc_out: 32,
            render_hidden: 128,
            render_narrow: 64,
            disc_width: 64,
            half_angle_feature: false,
            ggx_codes: false,
        }
    }

    /// Trainable on a 2-core CPU in a few hours: W = 16, ND_enc
    /// 297 -> 128 -> 128 -> 32, M_render 96 -> 64 x5 -> 32 -> 3, discriminator
    /// width 32 (same architecture, narrower layers).
    ///
    /// Cost of one training step at crop 128, 2 materials, each rendered
    /// under 1 input + 8 output configurations (18 frames = 294,912 pixel
    /// rows for the renderer). Forward GFLOP from [`super::est_flops`] and
    /// [`super::renderer_flops_per_row`]:
    ///
    /// | part (forward)            | paper | compact |
    /// |---------------------------|-------|---------|
    /// | M_est, 2 photos 128x128   | 520   | 35      |
    /// | ND_enc, 294,912 rows      | 323   | 35      |
    /// | M_render, 294,912 rows    | 51    | 15      |
    ///
    /// The paper's alternating step = M_est update (M_est forward + backward,
    /// M_render forward + input gradients) then renderer update (ND_enc and
    /// M_render forward + backward on the detached map); with ND_enc's
    /// output shared by both updates that is about 3x M_est + 3x ND_enc +
    /// 5x M_render forward costs: ~2.8 TFLOP per step at paper size, ~0.28
    /// TFLOP for `compact`. M_est at W = 16 is 16x cheaper than W = 64, and
    /// the narrower ND_enc is 9x cheaper per row.
    ///
    /// Measured on the 2-core development machine (`bench_train` test, debug
    /// build with optimised dependencies): 5.2 s per step with 2 threads
    /// (9.2 s with 1), i.e. about 2,000 steps in 3 hours. Per-row costs are
    /// memory-bound beyond the matmuls (encoding, activations), which is why
    /// M_render is also narrowed: with the paper's 128-wide M_render the
    /// step took 14.0 s instead of 9.2 s (1 thread).
    pub fn compact() -> Self {
        Self {
            name: "compact".into(),
            est_width: 16,
            enc_hidden: 128,
            render_hidden: 64,
            render_narrow: 32,
            disc_width: 32,
            ..Self::paper()
        }
    }

    /// `compact` with 8 direction-encoding frequencies instead of 16 (ND_enc
    /// reads 9 + 18 x 8 = 153 values). Where the direction components are
    /// dyadic rationals (all 0 where light and view meet along the normal,
    /// then 1/2, 1/4, ...) every cos(2^k pi v) of high k is 1 at once, and
    /// weights that cancel elsewhere add up: the high frequencies gave the
    /// co-located highlight a spike and rings (issue 15,
    /// `reports/frequencies.md`). 2^7 pi still resolves a pixel's change of
    /// direction at 256x256.
    pub fn compact_f8() -> Self {
        Self { name: "compact-f8".into(), enc_frequencies: 8, ..Self::compact() }
    }

    /// `compact` whose ND_enc also reads the log half angle
    /// ([`ModelConfig::half_angle_feature`]; issue 48's experiment).
    pub fn compact_h() -> Self {
        Self { name: "compact-h".into(), half_angle_feature: true, ..Self::compact() }
    }

    /// `compact-f8` whose ND_enc also reads the log half angle (the bundled
    /// model's layout plus one input column).
    pub fn compact_f8h() -> Self {
        Self { name: "compact-f8h".into(), half_angle_feature: true, ..Self::compact_f8() }
    }

    /// `compact` whose M_est writes GGX values through a teacher's frozen
    /// encoder ([`ModelConfig::ggx_codes`]; issue 48's experiment).
    pub fn compact_g() -> Self {
        Self { name: "compact-g".into(), ggx_codes: true, ..Self::compact() }
    }

    /// The same configuration with M_est writing neural codes directly (a
    /// `-g` suffix dropped from the name): the one a teacher of this
    /// renderer was trained for.
    pub fn without_ggx_codes(&self) -> Self {
        let name = if self.ggx_codes { self.name.strip_suffix("-g").unwrap_or(&self.name) } else { &self.name };
        Self { name: name.into(), ggx_codes: false, ..self.clone() }
    }

    /// For tests: the same architecture at toy widths (M_est W = 8,
    /// 1,338,176 parameters).
    pub fn tiny() -> Self {
        Self {
            name: "tiny".into(),
            est_width: 8,
            neural_channels: 16,
            enc_frequencies: 16,
            enc_hidden: 32,
            enc_out: 8,
            render_hidden: 16,
            render_narrow: 8,
            disc_width: 8,
            half_angle_feature: false,
            ggx_codes: false,
        }
    }

    /// A preset by name ([`PRESETS`]).
    pub fn preset(name: &str) -> Result<Self> {
        match name {
            "paper" => Ok(Self::paper()),
            "compact" => Ok(Self::compact()),
"compact-f8" => Ok(Self::compact_f8()),
            "compact-h" => Ok(Self::compact_h()),
            "compact-f8h" => Ok(Self::compact_f8h()),
            "compact-g" => Ok(Self::compact_g()),
            "tiny" => Ok(Self::tiny()),
            other => bail!("unknown model preset '{other}'; available presets: {}", PRESETS.join(", ")),
        }
    }

    /// Parses a TOML configuration; missing fields take the paper values.
    pub fn from_toml_str(text: &str) -> Result<Self> {
        let cfg: Self = toml::from_str(text).context("invalid model configuration TOML")?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Loads a TOML configuration file (see [`ModelConfig::from_toml_str`]).
    pub fn from_toml_file(path: impl AsRef<Path>) -> Result<Self> {
        let path = path.as_ref();
        let bytes = crate::io::read_input(path).with_context(|| format!("cannot read model config {}", path.display()))?;
        let text = String::from_utf8(bytes).with_context(|| format!("model config {} is not UTF-8 text", path.display()))?;
        Self::from_toml_str(&text).with_context(|| format!("in model config {}", path.display()))
    }

    /// TOML text of this configuration (round-trips through `from_toml_str`).
    pub fn to_toml_string(&self) -> Result<String> {
        Ok(toml::to_string(self)?)
    }

    /// Checks that the sizes describe a buildable network, within
    /// [`crate::limits::EST_WIDTH`] and [`crate::limits::LAYER_WIDTH`]
    /// (checked before any weight is allocated: the sizes may come from a
    /// file).
    pub fn validate(&self) -> Result<()> {
        ensure!(
            self.est_width >= 2 && self.est_width % 2 == 0,
            "est_width must be an even number >= 2 (HA layers split channels in halves), got {}",
            self.est_width
        );
        crate::limits::EST_WIDTH.check("est_width", self.est_width as u64)?;
        for (name, v) in [
            ("neural_channels", self.neural_channels),
            ("enc_hidden", self.enc_hidden),
            ("enc_out", self.enc_out),
            ("render_hidden", self.render_hidden),
            ("render_narrow", self.render_narrow),
            ("disc_width", self.disc_width),
        ] {
            ensure!(v >= 1, "{name} must be >= 1, got {v}");
            crate::limits::LAYER_WIDTH.check(name, v as u64)?;
        }
        ensure!(
            (0..=24).contains(&self.enc_frequencies),
            "enc_frequencies must be in 0..=24 (2^k must stay exact in f32), got {}",
            self.enc_frequencies
        );
        Ok(())
    }

    /// Width of ND_enc's input: the sinusoidal direction encoding, 9 + 2 *
    /// 9 * frequencies (297 for the paper), and the half-angle feature's
    /// column where the model has it.
    pub fn encoding_width(&self) -> i64 {
        9 + 18 * self.enc_frequencies + self.half_angle_feature as i64
    }

    /// Stable identifier: the name and a 64-bit FNV-1a hash of every size.
    /// Checkpoints record it so a model refuses weights of another shape.
    pub fn model_id(&self) -> String {
        let canonical = format!(
            "name={};est_width={};neural_channels={};enc_frequencies={};enc_hidden={};enc_out={};render_hidden={};render_narrow={};disc_width={}",
            self.name,
            self.est_width,
            self.neural_channels,
            self.enc_frequencies,
            self.enc_hidden,
            self.enc_out,
            self.render_hidden,
            self.render_narrow,
            self.disc_width
        );
        // Models without the feature keep the identifiers they always had.
        let canonical = if self.half_angle_feature { canonical + ";half_angle_feature=1" } else { canonical };
        let canonical = if self.ggx_codes { canonical + ";ggx_codes=1" } else { canonical };
        format!("{}-{:016x}", self.name, fnv1a64(canonical.as_bytes()))
    }
}

/// FNV-1a: tiny, and stable across Rust versions (unlike `DefaultHasher`).
fn fnv1a64(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_and_errors() {
        for name in PRESETS {
            let c = ModelConfig::preset(name).unwrap();
            assert_eq!(c.name, name);
            c.validate().unwrap();
        }
        assert_eq!(ModelConfig::paper().encoding_width(), 297);
        let err = ModelConfig::preset("huge").unwrap_err().to_string();
        assert!(err.contains("paper, compact, compact-f8, compact-h, compact-f8h, compact-g, tiny"), "{err}");
        assert_eq!(ModelConfig::compact_g().without_ggx_codes(), ModelConfig::compact());
        assert_eq!(ModelConfig::compact_f8h().encoding_width(), 154);
        assert_eq!(ModelConfig::compact_f8().encoding_width(), 153);
    }

    #[test]
    fn model_id_is_stable_and_distinguishes() {
        let p = ModelConfig::paper();
        assert_eq!(p.model_id(), ModelConfig::paper().model_id());
        assert!(p.model_id().starts_with("paper-"));
        assert_ne!(p.model_id(), ModelConfig::compact().model_id());
        let mut q = p.clone();
        q.enc_hidden = 593;
        assert_ne!(p.model_id(), q.model_id());
        // Pinned: changing the hash would orphan existing checkpoints.
        assert_eq!(fnv1a64(b"a"), 0xaf63dc4c8601ec8c);
    }

    #[test]
    fn toml_round_trip_and_partial() {
        let c = ModelConfig::compact();
        let text = c.to_toml_string().unwrap();
        assert_eq!(ModelConfig::from_toml_str(&text).unwrap(), c);
        let partial = ModelConfig::from_toml_str("name = \"mine\"\nest_width = 32\n").unwrap();
        assert_eq!(partial.est_width, 32);
        assert_eq!(partial.enc_hidden, 594);
        assert!(ModelConfig::from_toml_str("est_width = 7").is_err());
        assert!(ModelConfig::from_toml_str("bogus = 1").is_err());
        let e = format!("{:#}", ModelConfig::from_toml_str("est_width = 100000").unwrap_err());
        assert!(e.contains("est_width is 100000") && e.contains("FLASHMAT_MAX_EST_WIDTH"), "{e}");
        assert!(ModelConfig::from_toml_str("enc_hidden = 1000000000").is_err());
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("m.toml");
        std::fs::write(&path, text).unwrap();
        assert_eq!(ModelConfig::from_toml_file(&path).unwrap(), c);
    }
}
