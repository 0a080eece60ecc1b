//! Training hyper-parameters (REFERENCE section 5). The defaults are the
//! paper's values for the losses, their weights, the batch (2 materials x 8
//! outputs), the optimizers and the learning-rate schedule; two defaults
//! are CPU values instead, because the paper's take days on a GPU: the
//! model preset (`compact`; the paper's is `--preset paper`) and the crop
//! (128; the paper trains at 192, then 256). `docs/TRAINING.md` gives both
//! recipes.

use crate::baselines::TrainMethod;
use crate::model::ModelConfig;
use serde::{Deserialize, Serialize};

/// Which pixels the renderer's L1 data term uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
pub enum PixelSampling {
    /// 60% of pixels drawn with probability proportional to 1 / ||neural params|| (the paper's default).
    InverseNorm,
    /// 60% of pixels drawn with probability proportional to ||target RGB||^2.
    TargetNorm,
    /// Every pixel.
    All,
}

/// How the networks are updated each batch.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
pub enum UpdateScheme {
    /// The paper: M_est step (renderer frozen), then renderer step on the detached map.
    Alternating,
    /// One backward pass through both networks, full-image L1 (no pixel sampling).
    Combined,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrainConfig {
    /// What is trained: flashmat or one of the baselines. Absent from
    /// flashmat configurations (files written before the baselines).
    #[serde(default, skip_serializing_if = "TrainMethod::is_flashmat")]
    pub method: TrainMethod,
    /// Width preset; baselines use its U-Net width (and, for the
    /// relighting U-Net, its direction-code sizes). Default `compact`, a CPU
    /// value (the paper's sizes are the `paper` preset).
    pub model: ModelConfig,
    /// `procedural` or a dataset folder.
    pub data: String,
    /// Resolution materials are generated at before cropping (procedural data).
    pub material_size: usize,
    /// Procedural data from a bank of this many materials (the first
    /// training seeds), generated once in parallel when the run starts and
    /// drawn with random crops and the 8 symmetries of the square; 0: a
    /// fresh material every draw. A GPU step outruns the generator.
    #[serde(default)]
    pub bank: usize,
    /// Training crop (default 128, a CPU value; paper: 192, then 256).
    pub crop: usize,
    pub materials_per_batch: usize,
    pub outputs_per_material: usize,
    /// Train on LDR (clamped) input photos.
    pub ldr_input: bool,
    /// Hard shadows from height fields in the training renders (REFERENCE section 8).
    #[serde(default)]
    pub shadows: bool,
    /// Multiplies the height fields for shadows.
    #[serde(default = "unit_height_scale")]
    pub height_scale: f64,
    /// Run folder whose checkpoint gave the starting weights (fine-tuning;
    /// flashmat only). `None`: fresh networks from the seed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub init_from: Option<String>,
    /// Exported model file whose weights and step count continue a run
    /// whose checkpoint was lost (a GPU job's disk is gone after the job):
    /// fresh optimizers and discriminator, the step and data stream go on
    /// from the file's step count.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub warm_start: Option<String>,
    /// Teacher file (`flashmat train-teacher`): a fresh run starts from its
    /// renderer, and M_est's loss gains `weight_code` times the relative L1
    /// between its neural map and the teacher's codes of the true maps.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub teacher: Option<String>,
    /// Weight of the teacher-code term (0: none).
    #[serde(default)]
    pub weight_code: f64,
    /// Extra weight of glossy pixels in the code term (`losses::code_l1`; 0:
    /// every pixel alike).
    #[serde(default)]
    pub code_gloss_weight: f64,
    /// Weight of the GGX-value term (`losses::ggx_value_l1`, glossy pixels
    /// weighted by `code_gloss_weight`; 0: none): a model whose M_est writes
    /// GGX values (`ModelConfig::ggx_codes`) learns them from the true maps
    /// directly, beside the code term behind the encoder.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub weight_ggx_values: f64,
    /// The code term fades linearly to 0 at this step (0: constant weight),
    /// leaving the paper's losses alone for the rest of the run.
    #[serde(default)]
    pub code_until: u64,
    pub lr: f64,
    /// Multiplicative learning-rate decay applied every `lr_decay_every` steps (paper: 1.5% per 20,000).
    pub lr_decay: f64,
    pub lr_decay_every: u64,
    /// Linear learning-rate warm-up over the first steps (0: none, the paper).
    /// Without it the first Adam steps push M_render's outputs below zero,
    /// where the final LeakyReLU(0.001) passes a thousandth of the gradient.
    #[serde(default)]
    pub warmup_steps: u64,
    /// The adversarial term starts at this step (0: from the start, the
    /// paper). Until the renderer produces plausible images the
    /// discriminator's gradient only drowns the L1 signal.
    #[serde(default)]
    pub adv_start: u64,
    /// Straight-through gradient for M_render's final LeakyReLU(0.001) (see
    /// `MRender::straight_through_output`); inference is unchanged.
    #[serde(default)]
    pub straight_through_output: bool,
    /// From this step on, M_est's BatchNorm normalises with its running
    /// statistics (frozen) instead of the batch's (None: never, the paper).
    /// With 2 materials a step, batch statistics take away what the two
    /// share (their mean colour), which the network then cannot learn.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub frozen_bn_from: Option<u64>,
    /// Probability that a training material is recoloured (random hue turn
    /// and saturation scale of its diffuse and specular maps,
    /// `Svbrdf::recolour`); 0 is the paper's data. The procedural families
    /// tie chroma to texture (wood is brown), so without it M_est can guess
    /// colour from texture instead of reading it from the photo.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub colour_augment: f64,
    /// Share of dark procedural materials (diffuse albedo darkened,
    /// `ProceduralConfig::dark_probability`); 0 is the paper's data. Real
    /// materials are mostly darker than the families' own colours (issue 53).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub dark_share: f64,
    /// Share of saturated procedural materials (diffuse albedo given a
    /// fully saturated hue with a near-black channel,
    /// `ProceduralConfig::saturated_probability`); 0 is the paper's data.
    /// The families' colours are muted, and real saturated materials came
    /// back with blue the photos lack (issue 69).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub saturated_share: f64,
    /// Of each material's outputs, this many are co-located (the input's
    /// own view, then light and camera together elsewhere,
    /// `SampleConfig::colocated_outputs`); 0 is the paper's "reflect" only.
    #[serde(default, skip_serializing_if = "is_zero_count")]
    pub colocated_outputs: usize,
    /// Of each material's outputs, this many (before the co-located ones)
    /// light and view independently on the hemisphere, as the Hemisphere
    /// case (`SampleConfig::hemisphere_outputs`); 0 is the paper's.
    #[serde(default, skip_serializing_if = "is_zero_count")]
    pub hemisphere_outputs: usize,
    /// Outputs per material with the photo's camera and the light moved so
    /// the mirror highlight lands on the material
    /// (`SampleConfig::moved_highlight_outputs`); 0 is the paper's.
    #[serde(default)]
    pub moved_highlight_outputs: usize,
    /// Share of the materials whose input photo is taken as a phone takes
    /// it (`SampleConfig::phone_inputs`; needs `ldr_input`); 0 is the paper's.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub phone_inputs: f64,
    /// Those photos saved as JPEGs (`PhonePhotoConfig::jpeg_quality`,
    /// at the qualities phones use); needs `phone_inputs`.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub phone_jpeg: bool,
    /// Keep M_est's upsampling kernels checkerboard-free: projected
    /// (`MEst::project_checkerboard_free`) when the run starts or resumes
    /// and after every update, so a flat photo gives a flat neural map
    /// (false: the paper's free transposed convolutions).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub checkerboard_free: bool,
    /// Train the renderer (ND_enc + M_render) and the discriminator only:
    /// M_est is not stepped and runs in inference mode (BatchNorm on its
    /// running statistics), so its codes are exactly those `estimate`
    /// gives. For fixing what the renderer does with a trained M_est's
    /// codes (the co-located highlight) without moving M_est (false: the
    /// paper, both halves).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub freeze_estimator: bool,
    /// Train M_est only: ND_enc + M_render keep the warm start's weights
    /// (they take part in the graph but are never stepped) and there is
    /// no discriminator. For fixing what M_est writes (the colour of its
    /// codes) against a renderer that already renders them (false: the
    /// paper, both halves).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub freeze_renderer: bool,
    /// Model file (the same model; usually the warm start) whose renderer
    /// gives the targets of the outputs that are not co-located: its
    /// renders of the same neural map and directions instead of the GGX
    /// truth. The run then learns the co-located outputs' truth while
    /// holding the renderer to what it did everywhere else. Needs
    /// `freeze_estimator` and `colocated_outputs` (None: the truth for
    /// every output, the paper).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub anchor: Option<String>,
    pub weight_l1: f64,
    pub weight_lpips: f64,
    pub weight_adv: f64,
    /// Weight of the colour-balance term (`losses::chroma_l1`): the mean
    /// chromaticity of each render against the truth's. The log L1 barely
    /// sees a dark channel that is 1.5x too bright (blue's red); this term
    /// weighs every channel's share alike (0: none, the paper).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub weight_chroma: f64,
    /// Weight of the shift-consistency term (`losses::shift_consistency`):
    /// every material is photographed a second time with camera and flash
    /// moved by up to `shift_pixels` pixels, and M_est's codes of the two
    /// photos must agree where they overlap. A code describes the material
    /// at its pixel, not where the flash was; without the term M_est wrote
    /// the highlight's position into flat materials' codes (rings, and a
    /// hole where the highlight was under any other light). 0: none, the paper.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub weight_shift: f64,
    /// Weight of the lobe term (`losses::lobe_l1`, issue 48): L1 of ln(1 + R)
    /// at `lobe_pixels` random pixels of the batch under lights inside each
    /// pixel's true GGX lobe, rendered from M_est's codes there. The output
    /// renders put a glossy pixel's mirror direction in view on a few
    /// pixels at best; the renderer never learned to draw the lobe there,
    /// even from the best map (`flashmat eval --ceiling`). Both halves
    /// take it. 0: none, the paper.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub weight_lobe: f64,
    /// Pixels a step of the lobe term samples (over the whole batch).
    #[serde(default = "default_lobe_pixels")]
    pub lobe_pixels: usize,
    /// Share of the lobe term's pairs with a light inside the lobe; the rest
    /// take a cosine-distributed light at the same pixels and views
    /// (`losses::lobe_l1`). 1: lobe lights only.
    #[serde(default = "one", skip_serializing_if = "is_one")]
    pub lobe_share: f64,
    /// Share of the lobe term's views taken from the flash camera's cone
    /// instead of the hemisphere (`losses::lobe_l1`). 0: none.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub lobe_camera_share: f64,
    /// Share of the lobe lights drawn at a narrower spread than the pixel's
    /// own (`losses::LobeSampling::narrow_share`). 0: none.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub lobe_narrow_share: f64,
    /// Largest shift of the second photo in pixels (each axis).
    #[serde(default = "default_shift_pixels")]
    pub shift_pixels: usize,
    /// The shift term over the codes' scale with its gradient
    /// (`losses::shift_consistency`): shrinking every code no longer
    /// lowers it.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub shift_scale_free: bool,
    pub pixel_fraction: f64,
    pub pixel_sampling: PixelSampling,
    pub scheme: UpdateScheme,
    /// Clip the global gradient norm of each network to this value.
    pub grad_clip: Option<f64>,
    /// Total steps to train (a resumed run continues to this count).
    pub steps: u64,
    pub checkpoint_every: u64,
    pub preview_every: u64,
    pub seed: u64,
    /// Every material of a step draws its crop, recolouring and light/view
    /// configurations from its own random stream, keyed by (seed, step, its
    /// index in the global batch), so a global batch is the same at every
    /// world size (`Shard`). Set for runs launched by torchrun and kept by
    /// their resumes; plain runs draw a step's materials from one stream.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub material_streams: bool,
    /// This process's share of the global batch in a data-parallel run
    /// (not saved: a run resumes at any world size).
    #[serde(skip)]
    pub shard: Shard,
}

/// Which part of a step's global batch this process trains on: materials
/// `rank * B .. (rank + 1) * B` of `world * B`, B = `materials_per_batch`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    pub rank: usize,
    pub world: usize,
}

impl Default for Shard {
    fn default() -> Self {
        Self { rank: 0, world: 1 }
    }
}

impl Shard {
    /// A random stream of the trainer's own (`batches::step_rng`'s
    /// `stream`), distinct on every rank; rank 0 keeps the plain run's.
    pub fn stream(&self, stream: u64) -> u64 {
        stream ^ ((self.rank as u64) << 32)
    }
}

fn is_zero_count(v: &usize) -> bool {
    *v == 0
}

fn default_shift_pixels() -> usize {
    16
}

/// Pixels of the lobe term per step: a quarter of the teacher's samples,
/// a few hundredths of a step's output pixels at the CPU recipe.
pub const DEFAULT_LOBE_PIXELS: usize = 4096;

fn default_lobe_pixels() -> usize {
    DEFAULT_LOBE_PIXELS
}

fn one() -> f64 {
    1.0
}

fn is_one(v: &f64) -> bool {
    *v == 1.0
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

fn unit_height_scale() -> f64 {
    1.0
}

impl Default for TrainConfig {
    fn default() -> Self {
        Self {
            method: TrainMethod::Flashmat,
            model: ModelConfig::compact(),
            data: "procedural".into(),
            material_size: 256,
            bank: 0,
            crop: 128,
            materials_per_batch: 2,
            outputs_per_material: 8,
            ldr_input: false,
            shadows: false,
            height_scale: 1.0,
            init_from: None,
            warm_start: None,
            teacher: None,
            weight_code: 0.0,
            code_gloss_weight: 0.0,
            weight_ggx_values: 0.0,
            code_until: 0,
            lr: 1e-4,
            lr_decay: 0.985,
            lr_decay_every: 20_000,
            warmup_steps: 0,
            adv_start: 0,
            straight_through_output: false,
            frozen_bn_from: None,
            colour_augment: 0.0,
            dark_share: 0.0,
            saturated_share: 0.0,
            colocated_outputs: 0,
            hemisphere_outputs: 0,
            moved_highlight_outputs: 0,
            phone_inputs: 0.0,
            phone_jpeg: false,
            checkerboard_free: false,
            freeze_estimator: false,
            freeze_renderer: false,
            anchor: None,
            weight_l1: 1.0,
            weight_lpips: 0.01,
            weight_adv: 0.03,
            weight_chroma: 0.0,
            weight_shift: 0.0,
            weight_lobe: 0.0,
            lobe_pixels: DEFAULT_LOBE_PIXELS,
            lobe_share: 1.0,
            lobe_camera_share: 0.0,
            lobe_narrow_share: 0.0,
            shift_pixels: default_shift_pixels(),
            shift_scale_free: false,
            pixel_fraction: 0.6,
            pixel_sampling: PixelSampling::InverseNorm,
            scheme: UpdateScheme::Alternating,
            grad_clip: None,
            steps: 10_000,
            checkpoint_every: 250,
            preview_every: 250,
            seed: 1,
            material_streams: false,
            shard: Shard::default(),
        }
    }
}

impl TrainConfig {
    /// Side of the crops taken from the materials: the crop, plus the
    /// shift's margin when the shift-consistency term is on (both photos
    /// are cut from it, `batches::batch_for_step`).
    pub fn material_crop(&self) -> usize {
        if self.weight_shift > 0.0 {
            self.crop + self.shift_pixels
        } else {
            self.crop
        }
    }

    /// Learning rate at a step: linear warm-up, then the paper's step decay.
    pub fn lr_at(&self, step: u64) -> f64 {
        let warmup = if step < self.warmup_steps { (step + 1) as f64 / self.warmup_steps as f64 } else { 1.0 };
        warmup * self.lr * self.lr_decay.powi((step / self.lr_decay_every.max(1)) as i32)
    }

    /// Weight of the teacher-code term at a step (fades to 0 at `code_until`).
    pub fn code_weight_at(&self, step: u64) -> f64 {
        if self.code_until == 0 {
            self.weight_code
        } else if step >= self.code_until {
            0.0
        } else {
            self.weight_code * (1.0 - step as f64 / self.code_until as f64)
        }
    }

    /// Whether M_est's BatchNorm uses batch statistics (and updates its
    /// running ones) at a step; false from `frozen_bn_from` on.
    pub fn est_batch_stats_at(&self, step: u64) -> bool {
        self.frozen_bn_from.is_none_or(|from| step < from)
    }

    /// Weight of the adversarial term at a step (0 before `adv_start`).
    pub fn adv_weight_at(&self, step: u64) -> f64 {
        if step < self.adv_start {
            0.0
        } else {
            self.weight_adv
        }
    }

    /// Checks the configuration, its sizes against [`crate::limits`]
    /// before anything of those sizes is allocated (it may come from the
    /// command line or from a checkpoint's file).
    /// How the lobe term draws its pairs.
    pub fn lobe_sampling(&self) -> super::losses::LobeSampling {
        super::losses::LobeSampling { pixels: self.lobe_pixels, lobe_share: self.lobe_share, camera_share: self.lobe_camera_share, narrow_share: self.lobe_narrow_share }
    }

    pub fn validate(&self) -> anyhow::Result<()> {
        use crate::limits;
        anyhow::ensure!(self.crop % 8 == 0 && self.crop >= 32, "--crop must be a multiple of 8 and at least 32 (got {})", self.crop);
        limits::TRAIN_CROP.check("--crop", self.crop as u64)?;
        limits::MATERIAL_SIZE.check("the material size", self.material_size as u64)?;
        let (batch, outputs, crop) = (self.materials_per_batch as u64, self.outputs_per_material as u64, self.crop as u64);
        limits::STEP_PIXELS.check_product(
            format_args!("a training step (--batch {batch} x (--outputs {outputs} + 1) x --crop {crop} squared)"),
            &[batch, outputs.saturating_add(1), crop, crop],
        )?;
        anyhow::ensure!(self.weight_lobe == 0.0 || self.lobe_pixels >= 1, "--lobe-pixels must be at least 1");
        limits::STEP_PIXELS.check("--lobe-pixels", self.lobe_pixels as u64)?;
        anyhow::ensure!((0.0..=1.0).contains(&self.lobe_share), "--lobe-share must be within 0..1, got {}", self.lobe_share);
        anyhow::ensure!((0.0..=1.0).contains(&self.lobe_camera_share), "--lobe-camera-share must be within 0..1, got {}", self.lobe_camera_share);
        anyhow::ensure!((0.0..=1.0).contains(&self.lobe_narrow_share), "--lobe-narrow-share must be within 0..1, got {}", self.lobe_narrow_share);
        limits::BANK_PIXELS.check_product(
            format_args!("the material bank (--bank {} x {} squared)", self.bank, self.material_size),
            &[self.bank as u64, self.material_size as u64, self.material_size as u64],
        )?;
        anyhow::ensure!(self.materials_per_batch >= 1, "--batch must be at least 1");
        if let Some(c) = self.grad_clip {
            anyhow::ensure!(c.is_finite() && c > 0.0, "--grad-clip must be a finite number > 0 (got {c})");
        }
        anyhow::ensure!(self.lr_decay.is_finite() && self.lr_decay > 0.0, "the learning-rate decay must be a finite number > 0 (got {})", self.lr_decay);
        for (name, w) in [("L1", self.weight_l1), ("LPIPS", self.weight_lpips), ("adversarial", self.weight_adv), ("chromaticity", self.weight_chroma), ("shift-consistency", self.weight_shift), ("lobe", self.weight_lobe)] {
            anyhow::ensure!(w.is_finite() && w >= 0.0, "the {name} weight must be a finite number >= 0 (got {w})");
        }
        anyhow::ensure!(self.material_size >= self.crop, "material size {} is smaller than the crop {}", self.material_size, self.crop);
        anyhow::ensure!(!self.shift_scale_free || self.weight_shift > 0.0, "--shift-scale-free changes the shift term: give --shift-weight too");
        if self.weight_lobe > 0.0 {
            anyhow::ensure!(self.method.is_flashmat(), "--lobe-weight applies to --method flashmat only");
            anyhow::ensure!(self.scheme == UpdateScheme::Alternating, "--lobe-weight applies to --scheme alternating only");
        }
        if self.weight_shift > 0.0 {
            anyhow::ensure!(self.method.is_flashmat(), "--shift-weight applies to --method flashmat only");
            anyhow::ensure!(!self.freeze_estimator, "--shift-weight trains M_est: not with --freeze-estimator");
            anyhow::ensure!(self.scheme == UpdateScheme::Alternating, "--shift-weight applies to --scheme alternating only");
            anyhow::ensure!(
                self.shift_pixels >= 1 && self.shift_pixels < self.crop,
                "--shift-pixels must be between 1 and the crop minus 1 ({}), got {}",
                self.crop.saturating_sub(1),
                self.shift_pixels
            );
            anyhow::ensure!(
                self.material_size >= self.crop + self.shift_pixels,
                "--shift-pixels {}: the crop plus the shift ({}) is larger than the materials ({})",
                self.shift_pixels,
                self.crop + self.shift_pixels,
                self.material_size
            );
        }
        anyhow::ensure!(self.materials_per_batch >= 2 || self.weight_adv == 0.0, "the discriminator needs at least 2 materials per batch");
        anyhow::ensure!(self.outputs_per_material >= 1, "at least one output render per material");
        anyhow::ensure!(
            self.colocated_outputs <= self.outputs_per_material,
            "--colocated-outputs {} is more than the {} outputs per material",
            self.colocated_outputs,
            self.outputs_per_material
        );
        anyhow::ensure!(
            self.colocated_outputs + self.hemisphere_outputs <= self.outputs_per_material,
            "--hemisphere-outputs {} and --colocated-outputs {} are more than the {} outputs per material",
            self.hemisphere_outputs,
            self.colocated_outputs,
            self.outputs_per_material
        );
        anyhow::ensure!(
            self.colocated_outputs + self.hemisphere_outputs + self.moved_highlight_outputs <= self.outputs_per_material,
            "--moved-highlight-outputs {}, --hemisphere-outputs {} and --colocated-outputs {} are more than the {} outputs per material",
            self.moved_highlight_outputs,
            self.hemisphere_outputs,
            self.colocated_outputs,
            self.outputs_per_material
        );
        anyhow::ensure!((0.0..=1.0).contains(&self.phone_inputs), "--phone-inputs must lie in [0, 1], got {}", self.phone_inputs);
        anyhow::ensure!(self.phone_inputs == 0.0 || self.ldr_input, "--phone-inputs needs --ldr (a phone writes 8-bit photos)");
        anyhow::ensure!(!self.phone_jpeg || self.phone_inputs > 0.0, "--phone-jpeg needs --phone-inputs");
        anyhow::ensure!(self.pixel_fraction > 0.0 && self.pixel_fraction <= 1.0, "pixel fraction must be in (0, 1]");
        anyhow::ensure!(self.lr > 0.0 && self.lr.is_finite(), "learning rate must be positive");
        anyhow::ensure!(self.init_from.is_none() || self.warm_start.is_none(), "--init-from and --warm-start exclude each other");
        anyhow::ensure!(!self.checkerboard_free || self.method.is_flashmat(), "--checkerboard-free applies to --method flashmat only");
        anyhow::ensure!(self.weight_code >= 0.0 && self.weight_code.is_finite(), "--code-weight must be a finite number >= 0 (got {})", self.weight_code);
        anyhow::ensure!(self.weight_code == 0.0 || self.teacher.is_some(), "--code-weight needs --teacher FILE");
        anyhow::ensure!(
            !self.model.ggx_codes || self.teacher.is_some(),
            "a model whose M_est writes GGX values (compact-g) needs --teacher FILE: the teacher's encoder turns them into codes"
        );
        anyhow::ensure!(
            self.code_gloss_weight >= 0.0 && self.code_gloss_weight.is_finite(),
            "--code-gloss-weight must be a finite number >= 0 (got {})",
            self.code_gloss_weight
        );
        anyhow::ensure!(
            self.weight_ggx_values >= 0.0 && self.weight_ggx_values.is_finite(),
            "--ggx-value-weight must be a finite number >= 0 (got {})",
            self.weight_ggx_values
        );
        anyhow::ensure!(
            self.weight_ggx_values == 0.0 || self.model.ggx_codes,
            "--ggx-value-weight needs a model whose M_est writes GGX values (--preset compact-g)"
        );
        anyhow::ensure!(!self.freeze_estimator || self.method.is_flashmat(), "--freeze-estimator applies to --method flashmat only");
        anyhow::ensure!(!self.freeze_estimator || self.weight_code == 0.0, "--freeze-estimator excludes --code-weight (the teacher's code term trains M_est)");
        anyhow::ensure!(!self.freeze_estimator || self.weight_ggx_values == 0.0, "--freeze-estimator excludes --ggx-value-weight (the term trains M_est)");
        anyhow::ensure!(
            !self.freeze_estimator || (self.init_from.is_some() || self.warm_start.is_some()),
            "--freeze-estimator needs a trained M_est: give --warm-start or --init-from"
        );
        if self.freeze_renderer {
            anyhow::ensure!(!self.freeze_estimator, "--freeze-renderer and --freeze-estimator exclude each other (nothing would train)");
            anyhow::ensure!(self.method.is_flashmat(), "--freeze-renderer applies to --method flashmat only");
            anyhow::ensure!(self.init_from.is_some() || self.warm_start.is_some(), "--freeze-renderer needs a trained renderer: give --warm-start or --init-from");
            anyhow::ensure!(self.weight_adv == 0.0, "--freeze-renderer needs --adv-weight 0 (the discriminator is not trained)");
        }
        if self.anchor.is_some() {
            anyhow::ensure!(self.freeze_estimator, "--anchor needs --freeze-estimator (it holds the renderer, for a fixed M_est)");
            anyhow::ensure!(self.colocated_outputs >= 1, "--anchor needs --colocated-outputs N >= 1 (the outputs that still learn the truth)");
            anyhow::ensure!(self.scheme == UpdateScheme::Alternating, "--anchor applies to --scheme alternating only");
        }
        anyhow::ensure!(self.bank == 0 || self.data == "procedural", "--bank applies to procedural data only (got --data {})", self.data);
        anyhow::ensure!(self.height_scale >= 0.0 && self.height_scale.is_finite(), "height scale must be a finite number >= 0 (got {})", self.height_scale);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn paper_step_decay() {
        let c = TrainConfig::default();
        assert_eq!(c.lr_at(0), 1e-4);
        assert_eq!(c.lr_at(19_999), 1e-4);
        assert!((c.lr_at(20_000) - 0.985e-4).abs() < 1e-15);
        assert!((c.lr_at(45_000) - 1e-4 * 0.985f64.powi(2)).abs() < 1e-15);
    }

    #[test]
    fn warmup_and_adversarial_start() {
        let c = TrainConfig { warmup_steps: 4, adv_start: 10, ..Default::default() };
        assert_eq!(c.lr_at(0), 0.25e-4);
        assert_eq!(c.lr_at(1), 0.5e-4);
        assert_eq!(c.lr_at(3), 1e-4);
        assert_eq!(c.lr_at(4), 1e-4);
        assert_eq!(c.adv_weight_at(9), 0.0);
        assert_eq!(c.adv_weight_at(10), 0.03);
        assert_eq!(TrainConfig::default().adv_weight_at(0), 0.03);
    }

    #[test]
    fn validation() {
        assert!(TrainConfig::default().validate().is_ok());
        assert!(TrainConfig { crop: 100, ..Default::default() }.validate().is_err());
        assert!(TrainConfig { materials_per_batch: 1, ..Default::default() }.validate().is_err());
        assert!(TrainConfig { height_scale: -1.0, ..Default::default() }.validate().is_err());
        // Sizes beyond the limits, and clipping that would not clip.
        assert!(TrainConfig { crop: 100_000, material_size: 100_000, ..Default::default() }.validate().is_err());
        let e = TrainConfig { materials_per_batch: 100_000, ..Default::default() }.validate().unwrap_err().to_string();
        assert!(e.contains("--batch 100000") && e.contains("FLASHMAT_MAX_STEP_PIXELS"), "{e}");
        assert!(TrainConfig { bank: usize::MAX, ..Default::default() }.validate().is_err());
        for clip in [-1.0, 0.0, f64::NAN, f64::INFINITY] {
            assert!(TrainConfig { grad_clip: Some(clip), ..Default::default() }.validate().is_err(), "{clip}");
        }
        assert!(TrainConfig { grad_clip: Some(1.0), ..Default::default() }.validate().is_ok());
        // Hemisphere and co-located outputs share the material's outputs (8 by default).
        assert!(TrainConfig { hemisphere_outputs: 6, colocated_outputs: 2, ..Default::default() }.validate().is_ok());
        let e = TrainConfig { hemisphere_outputs: 7, colocated_outputs: 2, ..Default::default() }.validate().unwrap_err().to_string();
        assert!(e.contains("--hemisphere-outputs 7 and --colocated-outputs 2 are more than the 8 outputs"), "{e}");
        // So do the moved-highlight outputs.
        let e = TrainConfig { phone_inputs: 0.5, ..Default::default() }.validate().unwrap_err().to_string();
        assert!(e.contains("--phone-inputs needs --ldr "), "{e}");
        assert!(TrainConfig { phone_inputs: 0.5, ldr_input: true, ..Default::default() }.validate().is_ok());
        let e = TrainConfig { phone_jpeg: true, ldr_input: true, ..Default::default() }.validate().unwrap_err().to_string();
        assert!(e.contains("--phone-jpeg needs --phone-inputs"), "{e}");
        assert!(TrainConfig { moved_highlight_outputs: 2, hemisphere_outputs: 4, colocated_outputs: 2, ..Default::default() }.validate().is_ok());
        let e = TrainConfig { moved_highlight_outputs: 3, hemisphere_outputs: 4, colocated_outputs: 2, ..Default::default() }.validate().unwrap_err().to_string();
        assert!(e.contains("--moved-highlight-outputs 3, --hemisphere-outputs 4 and --colocated-outputs 2 are more than the 8 outputs"), "{e}");
    }

    #[test]
    fn method_field_is_absent_for_flashmat_and_round_trips_for_baselines() {
        let text = serde_json::to_string(&TrainConfig::default()).unwrap();
        assert!(!text.contains("method"), "{text}");
        let c = TrainConfig { method: TrainMethod::RelightUnet, ..Default::default() };
        let text = serde_json::to_string(&c).unwrap();
        assert!(text.contains("\"method\":\"relight-unet\""), "{text}");
        assert_eq!(serde_json::from_str::<TrainConfig>(&text).unwrap(), c);
    }

    #[test]
    fn configs_without_shadow_fields_still_load() {
        let mut v = serde_json::to_value(TrainConfig::default()).unwrap();
        let obj = v.as_object_mut().unwrap();
        obj.remove("shadows");
        obj.remove("height_scale");
        obj.remove("warmup_steps");
        obj.remove("adv_start");
        obj.remove("straight_through_output");
        obj.remove("bank");
        obj.remove("weight_code");
        obj.remove("code_until");
        obj.remove("code_gloss_weight");
        obj.remove("weight_ggx_values");
        let c: TrainConfig = serde_json::from_value(v).unwrap();
        assert_eq!(c, TrainConfig::default());
    }
}
