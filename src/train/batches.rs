//! Where training materials come from: the procedural stream or a dataset
//! folder, deterministic per (seed, step) so a resumed run sees the same
//! batches, prepared on a background thread so the trainer never waits.

use super::TrainConfig;
use crate::data::loaders::{open_dataset, random_crop, SvbrdfSource};
use crate::data::phone::PhonePhotoConfig;
use crate::data::procedural;
use crate::data::samples::{input_only, make_batch, SampleConfig, ShiftedPhotos, TrainingBatch};
use crate::svbrdf::height::ensure_height_field;
use crate::svbrdf::Svbrdf;
use anyhow::{anyhow, Result};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;
use std::sync::mpsc;
use std::sync::Arc;
use tch::Device;

/// RNG for everything random in one step (crops, light/view sampling).
pub fn step_rng(seed: u64, step: u64, stream: u64) -> Pcg64 {
    Pcg64::seed_from_u64(seed ^ step.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ stream.wrapping_mul(0xD1B5_4A32_D192_ED03))
}

/// The random stream `stream` (1 crops, 2 light/view, 3 recolouring, 4
/// shift) of the material at `index` of a step's global batch, for runs
/// with `TrainConfig::material_streams` (above the plain run's streams).
pub fn material_rng(seed: u64, step: u64, index: u64, stream: u64) -> Pcg64 {
    step_rng(seed, step, 16 + index * 8 + stream)
}

/// Global-batch indices of this process's materials of a step.
fn global_indices(cfg: &TrainConfig) -> std::ops::Range<u64> {
    let n = cfg.materials_per_batch as u64;
    let first = cfg.shard.rank as u64 * n;
    first..first + n
}

/// A source of training materials.
#[derive(Clone)]
pub enum MaterialStream {
    Procedural { config: procedural::ProceduralConfig },
    /// A bank of procedural materials, drawn with random symmetries.
    Bank(Arc<Vec<Svbrdf>>),
    /// One held-out material (`procedural-test:I`): the over-fitting experiment.
    Single(Arc<Svbrdf>),
    Dataset(Arc<dyn SvbrdfSource>),
}

impl MaterialStream {
    pub fn open(cfg: &TrainConfig) -> Result<Self> {
        let procedural_config = || procedural::ProceduralConfig {
            saturated_probability: cfg.saturated_share as f32,
            ..procedural::ProceduralConfig::with_dark_share(cfg.material_size, cfg.dark_share as f32)
        };
        if cfg.data == "procedural" && cfg.bank > 0 {
            Ok(Self::Bank(Arc::new(generate_bank(cfg.bank, &procedural_config()))))
        } else if cfg.data == "procedural" {
            Ok(Self::Procedural { config: procedural_config() })
        } else if let Some(index) = procedural::parse_test_material(&cfg.data)? {
            Ok(Self::Single(Arc::new(procedural::test_material(index, cfg.material_size))))
        } else {
            let ds = open_dataset(std::path::Path::new(&cfg.data))?;
            anyhow::ensure!(ds.len() > 0, "dataset {} holds no materials", cfg.data);
            Ok(Self::Dataset(Arc::from(ds)))
        }
    }

    /// The cropped (and, with `colour_augment`, recoloured) materials of
    /// training step `step`.
    pub fn materials(&self, cfg: &TrainConfig, step: u64) -> Result<Vec<Svbrdf>> {
        let crops = self.crops(cfg, step)?;
        if cfg.colour_augment <= 0.0 {
            return Ok(crops);
        }
        // Its own random stream: the crops and renders of a step stay those of a run without it.
        let mut rng = step_rng(cfg.seed, step, 3);
        let indices = global_indices(cfg);
        Ok(crops
            .into_iter()
            .zip(indices)
            .map(|(m, g)| {
                if cfg.material_streams {
                    rng = material_rng(cfg.seed, step, g, 3);
                }
                let (recolour, hue_turns, log_saturation) = (rng.random::<f64>() < cfg.colour_augment, rng.random::<f32>(), rng.random_range(-0.5f32..0.6));
                if recolour {
                    m.recolour(hue_turns, log_saturation.exp())
                } else {
                    m
                }
            })
            .collect())
    }

    fn crops(&self, cfg: &TrainConfig, step: u64) -> Result<Vec<Svbrdf>> {
        if cfg.material_streams {
            return global_indices(cfg).map(|g| self.material_of(cfg, step, g)).collect();
        }
        let mut rng = step_rng(cfg.seed, step, 1);
        let n = cfg.materials_per_batch as u64;
        // Names of dataset materials, for the errors of their crops.
        let mut names: Vec<String> = Vec::new();
        let full: Vec<Svbrdf> = match self {
            Self::Procedural { config } => {
                let seeds: Vec<u64> = (0..n).map(|i| procedural::training_seed(step * n + i)).collect();
                procedural::generate_many_with(&seeds, config)
            }
            Self::Single(m) => vec![m.as_ref().clone(); n as usize],
            Self::Bank(bank) => {
                // Crop first, then turn: the symmetry costs a crop's pixels, not a material's.
                return (0..n)
                    .map(|_| {
                        let m = &bank[rng.random_range(0..bank.len())];
                        let code = rng.random_range(0..8u8);
                        random_crop(m, cfg.material_crop(), &mut rng).map(|c| c.dihedral(code))
                    })
                    .collect();
            }
            Self::Dataset(ds) => (0..n)
                .map(|_| {
                    let i = rng.random_range(0..ds.len());
                    names.push(ds.name(i));
                    ds.load_named(i)
                })
                .collect::<Result<_>>()?,
        };
        let named = |k: usize, e: anyhow::Error| match names.get(k) {
            Some(name) => anyhow!("material {name}: {e:#}"),
            None => e,
        };
        // Loaded maps have no height field: integrate the whole material
        // before cropping (a crop's own integration would differ at its edges).
        let full = if cfg.shadows {
            full.into_iter().enumerate().map(|(k, mut m)| ensure_height_field(&mut m).map(|_| m).map_err(|e| named(k, e))).collect::<Result<Vec<_>>>()?
        } else {
            full
        };
        full.iter().enumerate().map(|(k, m)| random_crop(m, cfg.material_crop(), &mut rng).map_err(|e| named(k, e))).collect()
    }

    /// The cropped material at `index` of step `step`'s global batch, from
    /// its own random stream (`TrainConfig::material_streams`): procedural
    /// materials are the plain run's of a batch of the global size.
    fn material_of(&self, cfg: &TrainConfig, step: u64, index: u64) -> Result<Svbrdf> {
        let mut rng = material_rng(cfg.seed, step, index, 1);
        let global = (cfg.materials_per_batch * cfg.shard.world) as u64;
        let mut name = None;
        let mut full = match self {
            Self::Procedural { config } => procedural::generate_many_with(&[procedural::training_seed(step * global + index)], config).remove(0),
            Self::Single(m) => m.as_ref().clone(),
            Self::Bank(bank) => {
                let m = &bank[rng.random_range(0..bank.len())];
                let code = rng.random_range(0..8u8);
                return random_crop(m, cfg.material_crop(), &mut rng).map(|c| c.dihedral(code));
            }
            Self::Dataset(ds) => {
                let i = rng.random_range(0..ds.len());
                name = Some(ds.name(i));
                ds.load_named(i)?
            }
        };
        let named = |e: anyhow::Error| match &name {
            Some(name) => anyhow!("material {name}: {e:#}"),
            None => e,
        };
        if cfg.shadows {
            ensure_height_field(&mut full).map_err(named)?;
        }
        random_crop(&full, cfg.material_crop(), &mut rng).map_err(named)
    }
}

/// The first `count` training materials, generated on all cores, with a
/// progress bar (thousands take a minute on a 16-core machine).
pub fn generate_bank(count: usize, config: &procedural::ProceduralConfig) -> Vec<Svbrdf> {
    use indicatif::ParallelProgressIterator;
    use rayon::prelude::*;
    let bar = indicatif::ProgressBar::new(count as u64);
    if let Ok(style) = indicatif::ProgressStyle::with_template("material bank {bar:30} {pos}/{len}  {per_sec}  ETA {eta}") {
        bar.set_style(style);
    }
    let bank = (0..count as u64).into_par_iter().progress_with(bar.clone()).map(|i| procedural::generate(procedural::training_seed(i), config)).collect();
    bar.finish_and_clear();
    bank
}

/// Renders the batch of a step on `device`. With the shift-consistency
/// term the materials carry the shift's margin (`TrainConfig::material_crop`):
/// the batch is cut from each at one random offset, the second photo
/// (`TrainingBatch::shifted`) at another.
pub fn batch_for_step(cfg: &TrainConfig, materials: &[Svbrdf], step: u64, device: Device) -> Result<TrainingBatch> {
    let sample_cfg = SampleConfig {
        outputs_per_material: cfg.outputs_per_material,
        colocated_outputs: cfg.colocated_outputs,
        hemisphere_outputs: cfg.hemisphere_outputs,
        moved_highlight_outputs: cfg.moved_highlight_outputs,
        phone_inputs: cfg.phone_inputs,
        phone: PhonePhotoConfig::saving_jpeg(cfg.phone_jpeg),
        ldr_input: cfg.ldr_input,
        shadows: cfg.shadows,
        height_scale: cfg.height_scale,
        ..Default::default()
    };
    if cfg.material_streams && materials.len() > 1 {
        // One material at a time, each from its own streams, joined.
        let parts = materials.iter().zip(global_indices(cfg)).map(|(m, g)| batch_of(cfg, &sample_cfg, std::slice::from_ref(m), step, Some(g), device)).collect::<Result<Vec<_>>>()?;
        return TrainingBatch::concat(parts);
    }
    let index = cfg.material_streams.then(|| global_indices(cfg).start);
    batch_of(cfg, &sample_cfg, materials, step, index, device)
}

/// [`batch_for_step`] of `materials` drawing from the plain run's streams,
/// or (with `index`) from those of the one material at that index of the global batch.
fn batch_of(cfg: &TrainConfig, sample_cfg: &SampleConfig, materials: &[Svbrdf], step: u64, index: Option<u64>, device: Device) -> Result<TrainingBatch> {
    let rng_of = |stream| match index {
        Some(g) => material_rng(cfg.seed, step, g, stream),
        None => step_rng(cfg.seed, step, stream),
    };
    let mut rng = rng_of(2);
    if cfg.weight_shift <= 0.0 {
        return tch::no_grad(|| make_batch(materials, sample_cfg, &mut rng, device));
    }
    // Its own random stream, as the recolouring's.
    let mut shift_rng = rng_of(4);
    let (mut first, mut second, mut offsets) = (vec![], vec![], vec![]);
    for m in materials {
        let margin = m.height().min(m.width()).saturating_sub(cfg.crop);
        let mut corner = || (shift_rng.random_range(0..=margin), shift_rng.random_range(0..=margin));
        let (a, b) = (corner(), corner());
        first.push(m.crop(a.0, a.1, cfg.crop, cfg.crop)?);
        second.push(m.crop(b.0, b.1, cfg.crop, cfg.crop)?);
        offsets.push((b.0 as i64 - a.0 as i64, b.1 as i64 - a.1 as i64));
    }
    tch::no_grad(|| {
        let mut batch = make_batch(&first, sample_cfg, &mut rng, device)?;
        batch.shifted = Some(ShiftedPhotos { est_input: input_only(&second, sample_cfg, device)?, offsets });
        Ok(batch)
    })
}

/// Prepares the materials of upcoming steps on a background thread.
pub struct Prefetcher {
    rx: mpsc::Receiver<(u64, Result<Vec<Svbrdf>>)>,
    _worker: std::thread::JoinHandle<()>,
}

impl Prefetcher {
    pub fn start(stream: MaterialStream, cfg: TrainConfig, first_step: u64, depth: usize) -> Self {
        let (tx, rx) = mpsc::sync_channel(depth);
        let worker = std::thread::spawn(move || {
            for step in first_step.. {
                let item = stream.materials(&cfg, step);
                if tx.send((step, item)).is_err() {
                    break;
                }
            }
        });
        Self { rx, _worker: worker }
    }

    /// Materials for `step` (steps arrive in order).
    pub fn next(&self, step: u64) -> Result<Vec<Svbrdf>> {
        let (got, item) = self.rx.recv().map_err(|_| anyhow::anyhow!("the data thread stopped"))?;
        anyhow::ensure!(got == step, "data thread out of step ({got} != {step})");
        item
    }
}
