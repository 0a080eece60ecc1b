//! The two-stage network: M_est (photo -> neural material map) and the
//! neural renderer (ND_enc + M_render: neural params + directions ->
//! ln(1 + radiance)), plus the training-only conditional discriminator.
//!
//! Variables live in separate VarStores so training can alternate
//! optimizers: `est.*` (M_est), `renderer.*` (ND_enc and M_render) and
//! `disc.*` (the discriminator, see [`Discriminator::with_store`]).
//! Checkpoints ([`Model::save`]) hold `est.*` and `renderer.*` only.

/// Defines `NAME`, which runs `BODY` (an `#[inline(always)]` function of
/// the same arguments) built for AVX2 where the CPU has it and for the
/// baseline x86-64 otherwise, and `AVX2_NAME`, the AVX2 build alone (the
/// tests compare the two builds):
/// `avx2_dispatch!(/// docs
/// [unsafe] fn NAME / AVX2_NAME(args) => BODY);`
/// The `unsafe` form is for bodies with a safety contract, which `NAME`
/// then carries; the AVX2 build is always `unsafe` (the CPU must have AVX2).
macro_rules! avx2_dispatch {
    ($(#[$meta:meta])* unsafe fn $name:ident / $avx2:ident ($($arg:ident: $ty:ty),* $(,)?) => $body:ident) => {
        $(#[$meta])*
        #[allow(clippy::too_many_arguments)]
        unsafe fn $name($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                return $avx2($($arg),*);
            }
            $body($($arg),*)
        }
        avx2_dispatch!(@avx2 $name / $avx2 ($($arg: $ty),*) => $body);
    };
    ($(#[$meta:meta])* fn $name:ident / $avx2:ident ($($arg:ident: $ty:ty),* $(,)?) => $body:ident) => {
        $(#[$meta])*
        #[allow(clippy::too_many_arguments)]
        fn $name($($arg: $ty),*) {
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("avx2") {
                // SAFETY: the CPU has AVX2.
                return unsafe { $avx2($($arg),*) };
            }
            $body($($arg),*)
        }
        avx2_dispatch!(@avx2 $name / $avx2 ($($arg: $ty),*) => $body);
    };
    (@avx2 $name:ident / $avx2:ident ($($arg:ident: $ty:ty),*) => $body:ident) => {
        #[doc = concat!("[`", stringify!($name), "`] built for AVX2.\n\n# Safety\nAs [`", stringify!($name), "`], and the CPU must have AVX2.")]
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = "avx2")]
        #[allow(clippy::too_many_arguments)]
        unsafe fn $avx2($($arg: $ty),*) {
            $body($($arg),*)
        }
    };
}

pub mod config;
pub mod discriminator;
pub mod file;
pub mod ggx_codes;
pub(crate) mod layers;
pub mod m_est;
pub mod m_render;
pub mod nd_enc;
pub mod winograd;

pub use config::{ModelConfig, PRESETS};
pub use discriminator::Discriminator;
pub use file::{ModelInfo, MODEL_FORMAT, MODEL_VERSION};
pub use m_est::{est_flops, FoldedMEst, MEst};
pub use m_render::MRender;
pub use nd_enc::{encode_directions, NdEnc};

use anyhow::{ensure, Context, Result};
use std::collections::HashMap;
use std::path::Path;
use std::time::Instant;
use tch::{nn, Device, Kind, Tensor};

/// ND_enc + M_render: the per-pixel neural BRDF.
#[derive(Debug)]
pub struct NeuralRenderer {
    pub nd_enc: NdEnc,
    pub m_render: MRender,
}

impl NeuralRenderer {
    /// Variables `<p>.nd_enc.*` and `<p>.m_render.*` (p conventionally `renderer`).
    pub fn new(p: &nn::Path, cfg: &ModelConfig) -> Result<Self> {
        cfg.validate()?;
        Ok(Self { nd_enc: NdEnc::new(&(p / "nd_enc"), cfg), m_render: MRender::new(&(p / "m_render"), cfg) })
    }

    /// Renders whole images.
    /// neural_map: `[N, C, H, W]`; wi, wo: `[N, K, 3, H, W]` unit vectors
    /// (towards light and camera) -> ln(1 + R) `[N, K, 3, H, W]`.
    pub fn forward_maps(&self, neural_map: &Tensor, wi: &Tensor, wo: &Tensor) -> Result<Tensor> {
        self.render_code(neural_map, &self.encode_maps(wi, wo)?)
    }

    /// ND_enc of whole direction maps, reusable across renders of the same
    /// light/view configurations (e.g. by both updates of a training step).
    /// wi, wo: `[N, K, 3, H, W]` -> direction code `[N, K, enc_out, H, W]`
    /// (a permuted view of channels-last storage, which is what
    /// [`NeuralRenderer::render_code`] reads without copying).
    pub fn encode_maps(&self, wi: &Tensor, wo: &Tensor) -> Result<Tensor> {
        let d = wi.size();
        ensure!(d.len() == 5 && d[2] == 3, "wi must be [N, K, 3, H, W], got {d:?}");
        ensure!(wo.size() == d, "wo {:?} must match wi {d:?}", wo.size());
        let rows = |t: &Tensor| t.permute([0, 1, 3, 4, 2]);
        // Left in the forward's dtype (bf16 under autocast): render_code reads it.
        Ok(crate::precision::forward(wi.device(), || self.nd_enc.forward(&rows(wi), &rows(wo))).permute([0, 1, 4, 2, 3]))
    }

    /// M_render of a neural map under pre-encoded directions.
    /// neural_map: `[N, C, H, W]`; code: `[N, K, enc_out, H, W]` (from
    /// [`NeuralRenderer::encode_maps`]) -> ln(1 + R) `[N, K, 3, H, W]`.
    pub fn render_code(&self, neural_map: &Tensor, code: &Tensor) -> Result<Tensor> {
        let s = neural_map.size();
        ensure!(s.len() == 4, "neural map must be [N, C, H, W], got {s:?}");
        let (n, c, h, w) = (s[0], s[1], s[2], s[3]);
        ensure!(c == self.m_render.neural_channels, "neural map has {c} channels, the renderer expects {}", self.m_render.neural_channels);
        let d = code.size();
        let e = self.m_render.code_width();
        ensure!(
            d.len() == 5 && d[0] == n && d[2] == e && d[3] == h && d[4] == w,
            "direction code must be [N, K, {e}, H, W] = [{n}, K, {e}, {h}, {w}], got {d:?}"
        );
        let k = d[1];
        // Channels-last rows: params [N, 1, HW, C] broadcast against the
        // code [N, K, HW, E] in M_render's split first layer.
        let params = neural_map.permute([0, 2, 3, 1]).reshape([n, 1, h * w, c]);
        let code = code.permute([0, 1, 3, 4, 2]).reshape([n, k, h * w, e]);
        let out = crate::precision::to_f32(crate::precision::forward(params.device(), || self.m_render.forward(&params, &code))); // [N, K, HW, 3]
        Ok(out.view([n, k, h, w, 3]).permute([0, 1, 4, 2, 3]).contiguous())
    }

    /// Renders arbitrary rows (what a path tracer calls per shading point).
    /// params: `[R, C]`; wi, wo: `[R, 3]` -> ln(1 + R) `[R, 3]`.
    pub fn forward_rows(&self, params: &Tensor, wi: &Tensor, wo: &Tensor) -> Result<Tensor> {
        let s = params.size();
        ensure!(
            s.len() == 2 && s[1] == self.m_render.neural_channels,
            "params must be [R, {}], got {s:?}",
            self.m_render.neural_channels
        );
        for (name, t) in [("wi", wi), ("wo", wo)] {
            nd_enc::check_dirs(name, t)?;
            ensure!(t.size() == [s[0], 3], "{name} must be [R, 3] = [{}, 3], got {:?}", s[0], t.size());
        }
        let code = self.nd_enc.forward(wi, wo);
        Ok(self.m_render.forward(params, &code))
    }
}

/// M_est and the neural renderer with their VarStores.
#[derive(Debug)]
pub struct Model {
    pub config: ModelConfig,
    /// Holds `est.*`.
    pub est_vs: nn::VarStore,
    /// Holds `renderer.*`.
    pub renderer_vs: nn::VarStore,
    pub est: MEst,
    pub renderer: NeuralRenderer,
}


impl Model {
    /// Fresh, randomly initialised networks.
    pub fn new(config: &ModelConfig, device: Device) -> Result<Self> {
        config.validate()?;
        let est_vs = nn::VarStore::new(device);
        let renderer_vs = nn::VarStore::new(device);
        let est = MEst::new(&(est_vs.root() / "est"), config)?;
        let renderer = NeuralRenderer::new(&(renderer_vs.root() / "renderer"), config)?;
        Ok(Self { config: config.clone(), est_vs, renderer_vs, est, renderer })
    }

    /// See [`ModelConfig::model_id`].
    pub fn model_id(&self) -> String {
        self.config.model_id()
    }

    pub fn device(&self) -> Device {
        self.est_vs.device()
    }

    /// M_est forward (autograd as the caller's context).
    /// x: `[N, 4, H, W]` -> `[N, C, H, W]`.
    pub fn est_forward_t(&self, x: &Tensor, train: bool) -> Result<Tensor> {
        self.est.forward_t(x, train)
    }

    /// Inference: no autograd, eval-mode statistics folded into the
    /// convolutions (folding costs one pass over the weights; keep a
    /// [`FoldedMEst`] from [`MEst::fold_batchnorm`] for repeated calls).
    /// x: `[N, 4, H, W]` -> `[N, C, H, W]`.
    pub fn est_inference(&self, x: &Tensor) -> Result<Tensor> {
        self.est.fold_batchnorm().forward(x)
    }

    /// Every variable of M_est and the renderer (`est.*`, `renderer.*`,
    /// including BatchNorm running statistics), sorted by name. Shallow
    /// copies: they share storage with the model.
    pub fn named_variables(&self) -> Vec<(String, Tensor)> {
        let mut named: Vec<(String, Tensor)> = self.est_vs.variables().into_iter().chain(self.renderer_vs.variables()).collect();
        named.sort_by(|a, b| a.0.cmp(&b.0));
        named
    }

    /// Copies values into the model by name (e.g. from an archive). Every
    /// model variable must be present with its shape, and no other name.
    pub fn load_named(&mut self, named: &HashMap<String, Tensor>) -> Result<()> {
        let vars = self.named_variables();
        for n in named.keys() {
            ensure!(vars.iter().any(|(v, _)| v == n), "unexpected variable '{n}' for model '{}'", self.model_id());
        }
        for (name, mut var) in vars {
            let src = named.get(&name).with_context(|| format!("variable '{name}' is missing"))?;
            ensure!(src.size() == var.size(), "variable '{name}' has shape {:?}, the model expects {:?}", src.size(), var.size());
            let src = src.to_device(var.device()).to_kind(var.kind());
            tch::no_grad(|| var.copy_(&src));
        }
        Ok(())
    }

    /// Writes `est.*` and `renderer.*` (including BatchNorm running
    /// statistics) as a checksummed archive (see [`crate::archive`]) with the
    /// model id, the configuration, the method (`flashmat`) and `info` in the metadata. This is the
    /// exported-model format that `flashmat export` writes. `half` stores
    /// the large weight tensors as f16 ([`Archive::store_half`]).
    pub fn save(&self, path: impl AsRef<Path>, info: &ModelInfo, half: bool) -> Result<()> {
        file::save_model_file(path.as_ref(), self.named_variables(), file::FLASHMAT_METHOD, &self.model_id(), &self.config, info, half)
    }

    /// Builds the model a file written by [`Model::save`] describes and
    /// loads its weights. Damaged, truncated or foreign files, and any
    /// missing, extra or mis-shaped variable, are refused naming the file.
    pub fn load(path: impl AsRef<Path>, device: Device) -> Result<(Self, ModelInfo)> {
        let path = path.as_ref();
        let f = file::ModelFile::load(path)?;
        let ctx = || format!("model file {}", path.display());
        if f.method != file::FLASHMAT_METHOD {
            anyhow::bail!("{} holds a '{}' model, not a flashmat one (baselines are scored with `flashmat eval --model`)", ctx(), f.method);
        }
        let mut m = Self::new(&f.config, device)?;
        ensure!(f.model_id == m.model_id(), "{}: model id does not match its configuration", ctx());
        m.load_named(&f.archive.tensors.iter().map(|(k, v)| (k.clone(), v.shallow_clone())).collect()).with_context(ctx)?;
        let info = f.info;
        Ok((m, info))
    }

    /// The element-wise mean of several model files' weights (and BatchNorm
    /// running statistics): late checkpoints of one run scatter around a
    /// minimum, and their average sits nearer it than any one of them.
    /// The files must hold the same model and input range; the info is the
    /// first file's, with the largest step count of them all. Averaging unrelated runs
    /// is allowed but meaningless (their units do not line up).
    pub fn average(paths: &[impl AsRef<Path>], device: Device) -> Result<(Self, ModelInfo)> {
        ensure!(!paths.is_empty(), "nothing to average: give at least one model file");
        let (mut model, mut info) = Self::load(&paths[0], device)?;
        let mut sums: Vec<(String, Tensor)> = model.named_variables().into_iter().map(|(k, v)| (k, v.to_kind(Kind::Double))).collect();
        for path in &paths[1..] {
            let path = path.as_ref();
            let (m, i) = Self::load_expecting(path, device, &model.model_id())?;
            ensure!(i.ldr_input == info.ldr_input, "{}: trained on {} photos, the first file on {} ones", path.display(), range(i.ldr_input), range(info.ldr_input));
            for ((_, sum), (_, v)) in sums.iter_mut().zip(m.named_variables()) {
                *sum += v.to_kind(Kind::Double);
            }
            info.steps = info.steps.max(i.steps);
        }
        let n = paths.len() as f64;
        let mean: HashMap<String, Tensor> = sums.into_iter().map(|(k, s)| (k, s / n)).collect();
        model.load_named(&mean)?;
        Ok((model, info))
    }

    /// The same model with the direction encoding cut to `config`'s
    /// frequencies: the first ND_enc layer keeps its columns for v and for
    /// sin / cos(2^k pi v) with k below the new count, everything else is
    /// copied. `config` may differ from the model's only in
    /// `enc_frequencies` (not more than the model's) and its name. The
    /// renders change by what the dropped columns contributed (a starting
    /// point for a fine-tune, `reports/frequencies.md`).
    pub fn truncate_frequencies(&self, config: &ModelConfig) -> Result<Self> {
        let (n, keep) = (self.config.enc_frequencies, config.enc_frequencies);
        ensure!(keep <= n, "the configuration has {keep} direction frequencies, the model only {n}");
        let same_otherwise = ModelConfig { name: self.config.name.clone(), enc_frequencies: n, ..config.clone() };
        ensure!(same_otherwise == self.config, "the configuration '{}' differs from the model's in more than its frequencies and name", config.name);
        let mut truncated = Self::new(config, self.device())?;
        let mut named: HashMap<String, Tensor> = self.named_variables().into_iter().collect();
        let first = named.get(FIRST_ENCODING_LAYER).with_context(|| format!("{FIRST_ENCODING_LAYER} is missing"))?;
        // Columns: [v (9) | sin, k-major (n x 9) | cos (n x 9) | half angle (0 or 1)] (`NdEnc::forward`).
        let mut columns = vec![first.narrow(1, 0, 9 + 9 * keep), first.narrow(1, 9 + 9 * n, 9 * keep)];
        if config.half_angle_feature {
            columns.push(first.narrow(1, 9 + 18 * n, 1));
        }
        let kept = Tensor::cat(&columns, 1);
        named.insert(FIRST_ENCODING_LAYER.into(), kept);
        truncated.load_named(&named)?;
        Ok(truncated)
    }

    /// The same model whose ND_enc also reads the log half angle
    /// (`ModelConfig::half_angle_feature`), named `name`: the first ND_enc
    /// layer gains a zero column for it, so every render is unchanged until
    /// training moves it (the warm start of issue 48's experiment).
    pub fn with_half_angle_feature(&self, name: &str) -> Result<Self> {
        ensure!(!self.config.half_angle_feature, "the model already reads the half-angle feature");
        let config = ModelConfig { name: name.into(), half_angle_feature: true, ..self.config.clone() };
        let mut widened = Self::new(&config, self.device())?;
        let mut named: HashMap<String, Tensor> = self.named_variables().into_iter().collect();
        let first = named.get(FIRST_ENCODING_LAYER).with_context(|| format!("{FIRST_ENCODING_LAYER} is missing"))?;
        let zero = Tensor::zeros([first.size()[0], 1], (first.kind(), first.device()));
        named.insert(FIRST_ENCODING_LAYER.into(), Tensor::cat(&[first.shallow_clone(), zero], 1));
        widened.load_named(&named)?;
        Ok(widened)
    }

    /// Loads a model file and checks that it is the expected model id.
    pub fn load_expecting(path: impl AsRef<Path>, device: Device, model_id: &str) -> Result<(Self, ModelInfo)> {
        let (m, info) = Self::load(&path, device)?;
        ensure!(
            m.model_id() == model_id,
            "{} holds model '{}', expected '{model_id}' (another preset or configuration)",
            path.as_ref().display(),
            m.model_id()
        );
        Ok((m, info))
    }
}

/// ND_enc's first layer, the one that reads the direction encoding.
const FIRST_ENCODING_LAYER: &str = "renderer.nd_enc.0.weight";

/// Number of trainable scalars in a VarStore.
pub fn count_trainable(vs: &nn::VarStore) -> i64 {
    vs.trainable_variables().iter().map(|t| t.numel() as i64).sum()
}

/// FLOPs per row of ND_enc + M_render.
pub fn renderer_flops_per_row(cfg: &ModelConfig) -> f64 {
    NdEnc::flops_per_row(cfg) + MRender::flops_per_row(cfg)
}

/// Inference timings from [`bench_infer`].
#[derive(Clone, Debug, serde::Serialize)]
pub struct InferTimings {
    pub model_id: String,
    pub size: usize,
    pub threads: i32,
    pub runs: usize,
    /// Median seconds of one M_est forward (folded BatchNorm, no autograd),
    /// over the whole photo or layer by layer in tiles of this core side.
    pub est_s: f64,
    pub tile_core: Option<i64>,
    /// Median seconds of ND_enc + M_render for one size x size frame.
    pub render_s: f64,
    pub est_gflop: f64,
    pub render_gflop: f64,
    /// Seconds of one naive M_est forward (eval-mode BatchNorm, autograd
    /// recording), the baseline the inference path is compared with.
    /// Whole-photo forwards only (the baselines keep every activation).
    pub naive_est_s: Option<f64>,
    /// Median seconds of the folded M_est forward with every conv direct
    /// (no Winograd), the baseline of [`crate::model::winograd`].
    pub direct_est_s: Option<f64>,
    /// Median seconds of the frame with the direction encoding in tensor
    /// operations ([`crate::reference_paths`]), the baseline of the host
    /// encoding.
    pub reference_render_s: f64,
}

impl std::fmt::Display for InferTimings {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let how = match self.tile_core {
            Some(core) => format!(" layer by layer in tiles of {core} px"),
            None => String::new(),
        };
        write!(f, "{} @ {}x{} ({} threads, median of {}): M_est{how} {:.3} s ({:.1} GFLOP, {:.1} GFLOP/s", self.model_id, self.size, self.size, self.threads, self.runs, self.est_s, self.est_gflop, self.est_gflop / self.est_s)?;
        if let Some(d) = self.direct_est_s {
            write!(f, "; every conv direct, no Winograd: {d:.3} s, {:.2}x slower", d / self.est_s)?;
        }
        if let Some(n) = self.naive_est_s {
            write!(f, "; naive eval-mode forward with autograd {n:.3} s, {:.2}x slower", n / self.est_s)?;
        }
        write!(
            f,
            "); ND_enc+M_render {:.3} s/frame ({:.1} GFLOP, {:.1} GFLOP/s; direction encoding in tensor operations: {:.3} s, {:.2}x slower)",
            self.render_s,
            self.render_gflop,
            self.render_gflop / self.render_s,
            self.reference_render_s,
            self.reference_render_s / self.render_s
        )
    }
}

fn sync(device: Device) {
    if let Device::Cuda(i) = device {
        tch::Cuda::synchronize(i as i64);
    }
}

fn median_time(runs: usize, device: Device, mut f: impl FnMut() -> Result<()>) -> Result<f64> {
    f()?; // warm-up
    sync(device);
    let mut times = Vec::with_capacity(runs);
    for _ in 0..runs {
        let t = Instant::now();
        f()?;
        sync(device);
        times.push(t.elapsed().as_secs_f64());
    }
    times.sort_by(|a, b| a.total_cmp(b));
    Ok(times[times.len() / 2])
}

/// Times inference of a randomly initialised model: one M_est forward of a
/// size x size photo (folded BatchNorm, no autograd) and ND_enc + M_render
/// for one size x size frame; medians of 3 runs after a warm-up. Uses the
/// current `tch::get_num_threads()`.
///
/// Measured at 256x256 on the 2-core development machine (the `flashmat`
/// binary: OMP_WAIT_POLICY=PASSIVE, then without GOMP_SPINCOUNT, freed
/// memory kept in the heap; 2 threads): paper M_est 6.1 s with the default
/// Winograd policy against 7.6 s with every conv direct, ND_enc + M_render
/// 1.2 s/frame; compact 0.79 s and 0.23 s/frame (`reports/inference-speed.md`; the machine is
/// shared, expect +-15%). The authors' PyTorch M_est takes about 20 s there.
pub fn bench_infer(cfg: &ModelConfig, size: usize, device: Device) -> Result<InferTimings> {
    bench_infer_runs(cfg, size, device, 3, None)
}

/// [`bench_infer`] with a chosen number of timed runs, M_est over the
/// whole photo (`tile_core` None, with the direct and naive baselines) or
/// layer by layer in tiles of that core side (what `--max-memory` plans
/// for large photos; no baselines, they would hold every activation).
pub fn bench_infer_runs(cfg: &ModelConfig, size: usize, device: Device, runs: usize, tile_core: Option<i64>) -> Result<InferTimings> {
    ensure!(runs >= 1, "need at least one timed run");
    let model = Model::new(cfg, device)?;
    let folded = model.est.fold_batchnorm();
    let s = size as i64;
    let opts = (Kind::Float, device);
    let (wi, wo) = crate::data::samples::input_directions(size, size, 28.0, device);
    let x = Tensor::cat(&[Tensor::rand([1, 3, s, s], opts), crate::svbrdf::render::half_vector_z(&wi, &wo)], 1);
    drop((wi, wo));
    let forward = |x: &Tensor| match tile_core {
        Some(core) => folded.forward_layerwise(x, core, || {}),
        None => folded.forward(x),
    };
    let est_s = median_time(runs, device, || forward(&x).map(drop))?;
    let map = forward(&x)?;
    let (mut direct_est_s, mut naive_est_s) = (None, None);
    if tile_core.is_none() {
        let mut direct = model.est.fold_batchnorm();
        direct.set_winograd(None);
        direct_est_s = Some(median_time(runs, device, || direct.forward(&x).map(drop))?);
        drop(direct);
        let t0 = Instant::now();
        let _ = model.est.forward_t(&x, false)?;
        sync(device);
        naive_est_s = Some(t0.elapsed().as_secs_f64());
    }
    drop(x);
    let dirs = |z: f32| {
        let v = Tensor::randn([1, 1, 3, s, s], opts) * 0.3 + Tensor::from_slice(&[0.0f32, 0.0, z]).to_device(device).view([1, 1, 3, 1, 1]);
        &v / v.square().sum_dim_intlist([2i64].as_slice(), true, Kind::Float).sqrt()
    };
    let (wi, wo) = (dirs(1.0), dirs(1.0));
    // A tiled photo's frame in bands of rows, as `relight` streams it.
    let band = if tile_core.is_some() { 256.min(s) } else { s };
    let frame = || -> Result<()> {
        for r in (0..s).step_by(band as usize) {
            let n = band.min(s - r);
            drop(model.renderer.forward_maps(&map.narrow(2, r, n), &wi.narrow(3, r, n), &wo.narrow(3, r, n))?);
        }
        Ok(())
    };
    let render_s = tch::no_grad(|| median_time(runs, device, frame))?;
    let reference_render_s = crate::reference_paths::with(|| tch::no_grad(|| median_time(runs, device, frame)))?;
    let px = (s * s) as f64;
    Ok(InferTimings {
        model_id: cfg.model_id(),
        size,
        threads: tch::get_num_threads(),
        runs,
        est_s,
        tile_core,
        render_s,
        est_gflop: est_flops(cfg, s, s) / 1e9,
        render_gflop: renderer_flops_per_row(cfg) * px / 1e9,
        naive_est_s,
        direct_est_s,
        reference_render_s,
    })
}

/// How a model file's input range is named in messages.
fn range(ldr_input: bool) -> &'static str {
    if ldr_input {
        "8-bit (LDR)"
    } else {
        "HDR"
    }
}

#[cfg(test)]
mod tests;
