//! Adam written out with tensors so that its moment estimates can be saved
//! in checkpoints (tch's built-in optimizer does not expose its state) and a
//! resumed run continues bit-for-bit.

use crate::archive::Archive;
use anyhow::{Context, Result};
use rayon::prelude::*;
use std::collections::{BTreeMap, HashMap};
use tch::Tensor;

/// Elements per rayon task of the fused update (the update streams memory;
/// 64 Ki floats keep a task's four buffers in L2).
const CHUNK: usize = 1 << 16;

/// A contiguous f32 CPU tensor's buffer: what the fused update reads and
/// writes in place.
struct HostF32 {
    ptr: *mut f32,
    len: usize,
}

impl HostF32 {
    /// # Safety
    /// Nothing may write the tensor while the slice lives.
    unsafe fn slice<'a>(&self) -> &'a [f32] {
        std::slice::from_raw_parts(self.ptr, self.len)
    }

    /// # Safety
    /// Nothing else may read or write the tensor while the slice lives.
    unsafe fn slice_mut<'a>(&self) -> &'a mut [f32] {
        std::slice::from_raw_parts_mut(self.ptr, self.len)
    }
}

/// The buffer of `t` when it is a contiguous f32 CPU tensor.
fn host_f32(t: &Tensor) -> Option<HostF32> {
    (t.device() == tch::Device::Cpu && t.kind() == tch::Kind::Float && t.is_contiguous() && t.numel() > 0)
        .then(|| HostF32 { ptr: t.data_ptr() as *mut f32, len: t.numel() })
}

/// One update's constants.
struct Coefficients {
    beta1: f64,
    beta2: f64,
    /// Bias corrections 1 - beta^t.
    bc1: f64,
    bc2: f64,
    eps: f64,
    lr: f64,
    /// Gradient scale of the norm clipping (1 without).
    scale: f64,
}

impl Coefficients {
    /// The update with tensor operations (any device or layout):
    /// m = b1 m + (1 - b1) g; v = b2 v + (1 - b2) g^2;
    /// p -= lr (m / bc1) / (sqrt(v / bc2) + eps).
    fn with_tensors(&self, p: &Tensor, g: &Tensor, m: &Tensor, v: &Tensor) {
        let g = if self.scale != 1.0 { g * self.scale } else { g.shallow_clone() };
        let (mut m, mut v) = (m.shallow_clone(), v.shallow_clone());
        let _ = m.g_mul_scalar_(self.beta1).g_add_(&(&g * (1.0 - self.beta1)));
        let _ = v.g_mul_scalar_(self.beta2).g_add_(&(g.square() * (1.0 - self.beta2)));
        let denom = (&v / self.bc2).sqrt() + self.eps;
        let update = (&m / self.bc1) / denom * self.lr;
        let _ = p.shallow_clone().g_sub_(&update);
    }

    /// The same update in one pass over the four buffers, each operation
    /// rounded to f32 in the tensor version's order (which makes its
    /// temporaries: about 20 reads and writes of every element, against 7
    /// here). p, m, v updated in place; all four the same length.
    fn fused(&self, p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32]) {
        let f = |x: f64| x as f32;
        let (b1, b2, ob1, ob2) = (f(self.beta1), f(self.beta2), f(1.0 - self.beta1), f(1.0 - self.beta2));
        let (bc1, bc2, eps, lr, scale) = (f(self.bc1), f(self.bc2), f(self.eps), f(self.lr), f(self.scale));
        let scaled = self.scale != 1.0;
        p.par_chunks_mut(CHUNK).zip(g.par_chunks(CHUNK)).zip(m.par_chunks_mut(CHUNK)).zip(v.par_chunks_mut(CHUNK)).for_each(|(((p, g), m), v)| {
            for i in 0..p.len() {
                let g = if scaled { g[i] * scale } else { g[i] };
                m[i] = m[i] * b1 + g * ob1;
                v[i] = v[i] * b2 + (g * g) * ob2;
                let denom = (v[i] / bc2).sqrt() + eps;
                p[i] -= ((m[i] / bc1) / denom) * lr;
            }
        });
    }
}

pub struct Adam {
    /// Trainable parameters by name (sorted for a deterministic update order).
    params: BTreeMap<String, Tensor>,
    exp_avg: BTreeMap<String, Tensor>,
    exp_avg_sq: BTreeMap<String, Tensor>,
    pub beta1: f64,
    pub beta2: f64,
    pub eps: f64,
    /// Number of updates applied (for bias correction).
    pub steps: i64,
    /// Updates contiguous f32 CPU tensors in one pass of Rust (the default);
    /// false runs the tensor operations everywhere (the reference for
    /// `bench train`).
    pub fused: bool,
}

impl Adam {
    /// params: the trainable variables of one network (name -> tensor).
    pub fn new(params: HashMap<String, Tensor>) -> Self {
        let params: BTreeMap<String, Tensor> = params.into_iter().filter(|(_, t)| t.requires_grad()).collect();
        let exp_avg = params.iter().map(|(k, v)| (k.clone(), v.zeros_like())).collect();
        let exp_avg_sq = params.iter().map(|(k, v)| (k.clone(), v.zeros_like())).collect();
        Self { params, exp_avg, exp_avg_sq, beta1: 0.9, beta2: 0.999, eps: 1e-8, steps: 0, fused: true }
    }

    /// The trainable parameters, in the update's (name) order.
    pub fn params(&self) -> impl Iterator<Item = &Tensor> {
        self.params.values()
    }

    pub fn zero_grad(&mut self) {
        for p in self.params.values() {
            let mut g = p.grad();
            if g.defined() {
                let _ = g.detach_().zero_();
            }
        }
    }

    /// Global L2 norm of the current gradients (NaN/Inf if any gradient is).
    pub fn grad_norm(&self) -> f64 {
        let mut total = 0f64;
        for p in self.params.values() {
            let g = p.grad();
            if !g.defined() {
                continue;
            }
            total += match host_f32(&g).filter(|_| self.fused) {
                // SAFETY: a contiguous f32 CPU gradient, read while no update runs.
                // The chunks' sums are added in order (rayon's own reduction
                // pairs them as its threads happen to split the work), so the
                // norm, and a clipped step, repeat exactly run to run.
                Some(g) => unsafe { g.slice() }.par_chunks(CHUNK).map(|c| c.iter().map(|&x| (x * x) as f64).sum::<f64>()).collect::<Vec<f64>>().iter().sum::<f64>(),
                None => g.square().sum(tch::Kind::Double).double_value(&[]),
            };
        }
        total.sqrt()
    }

    /// Applies one update with learning rate `lr`, first scaling gradients
    /// so that their global norm is at most `clip` when given.
    pub fn step(&mut self, lr: f64, clip: Option<f64>) {
        let scale = match clip {
            Some(max) => {
                let n = self.grad_norm();
                if n > max { max / (n + 1e-12) } else { 1.0 }
            }
            None => 1.0,
        };
        self.steps += 1;
        let bc1 = 1.0 - self.beta1.powi(self.steps as i32);
        let bc2 = 1.0 - self.beta2.powi(self.steps as i32);
        let c = Coefficients { beta1: self.beta1, beta2: self.beta2, bc1, bc2, eps: self.eps, lr, scale };
        tch::no_grad(|| {
            for (name, p) in &self.params {
                let g = p.grad();
                if !g.defined() {
                    continue;
                }
                let (m, v) = (&self.exp_avg[name], &self.exp_avg_sq[name]);
                let buffers = if self.fused { [host_f32(p), host_f32(&g), host_f32(m), host_f32(v)] } else { [None, None, None, None] };
                match buffers {
                    // SAFETY: four distinct contiguous f32 CPU buffers of
                    // the same length (the parameter, its gradient, its two
                    // moments), nothing else touches them during the update.
                    [Some(p), Some(g), Some(m), Some(v)] if [g.len, m.len, v.len] == [p.len; 3] => unsafe { c.fused(p.slice_mut(), g.slice(), m.slice_mut(), v.slice_mut()) },
                    _ => c.with_tensors(p, &g, m, v),
                }
            }
        });
    }

    /// The first moment of the variable `name` (after one update from
    /// fresh moments: (1 - beta1) times its gradient).
    pub fn first_moment(&self, name: &str) -> Option<&Tensor> {
        self.exp_avg.get(name)
    }

    /// Names of the variables this optimizer updates, sorted.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.params.keys().map(String::as_str)
    }

    /// Stores the moments under `prefix` and the step count in metadata.
    pub fn save_into(&self, archive: &mut Archive, prefix: &str) {
        for (k, v) in &self.exp_avg {
            archive.insert(format!("{prefix}m/{k}"), v);
        }
        for (k, v) in &self.exp_avg_sq {
            archive.insert(format!("{prefix}v/{k}"), v);
        }
        archive.set_meta(&format!("{prefix}steps"), self.steps.to_string());
    }

    pub fn load_from(&mut self, archive: &Archive, prefix: &str) -> Result<()> {
        for (kind, store) in [("m", &self.exp_avg), ("v", &self.exp_avg_sq)] {
            for (k, dst) in store {
                let src = archive.tensor(&format!("{prefix}{kind}/{k}")).context("optimizer state")?;
                anyhow::ensure!(src.size() == dst.size(), "optimizer state for '{k}' has the wrong shape");
                tch::no_grad(|| dst.shallow_clone().copy_(&src.to_device(dst.device())));
            }
        }
        self.steps = archive.meta(&format!("{prefix}steps"))?.parse().context("optimizer step count")?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tch::{Device, Kind};

    #[test]
    fn first_step_moves_by_lr_against_gradient_sign() {
        // With bias correction, the first Adam step is lr * g / (|g| + eps).
        let w = Tensor::from_slice(&[1.0f32, -2.0, 0.5]).set_requires_grad(true);
        let mut opt = Adam::new([("w".to_string(), w.shallow_clone())].into());
        let loss = (&w * Tensor::from_slice(&[3.0f32, -1.0, 0.0])).sum(Kind::Float);
        loss.backward();
        opt.step(0.1, None);
        let got: Vec<f32> = Vec::try_from(w.detach()).unwrap();
        assert!((got[0] - 0.9).abs() < 1e-6 && (got[1] + 1.9).abs() < 1e-6 && (got[2] - 0.5).abs() < 1e-6, "{got:?}");
    }

    #[test]
    fn minimises_a_quadratic_and_clips() {
        let w = Tensor::from_slice(&[5.0f32, -3.0]).set_requires_grad(true);
        let mut opt = Adam::new([("w".to_string(), w.shallow_clone())].into());
        for _ in 0..500 {
            opt.zero_grad();
            w.square().sum(Kind::Float).backward();
            opt.step(0.05, Some(1.0));
        }
        assert!(w.abs().max().double_value(&[]) < 0.05);
        assert_eq!(opt.steps, 500);
    }

    /// The fused CPU update against the tensor one, element by element, over
    /// steps with and without clipping (measured: the moments bit for bit,
    /// the weights to one f32 ulp).
    #[test]
    fn fused_update_matches_the_tensor_update() {
        let n = 3 * CHUNK as i64 + 77; // several rayon tasks and a ragged end
        let init = Tensor::randn([n], (tch::Kind::Float, Device::Cpu));
        let (a, b) = (init.copy().set_requires_grad(true), init.copy().set_requires_grad(true));
        let mut fused = Adam::new([("w".to_string(), a.shallow_clone())].into());
        let mut plain = Adam::new([("w".to_string(), b.shallow_clone())].into());
        plain.fused = false; // tensor operations, as on a GPU
        let mut moved = 0f64;
        for step in 0..4 {
            let target = Tensor::randn([n], (tch::Kind::Float, Device::Cpu)) * (step + 1) as f64;
            for (w, opt) in [(&a, &mut fused), (&b, &mut plain)] {
                opt.zero_grad();
                (w * &target).sum(Kind::Float).backward();
            }
            assert!((fused.grad_norm() - plain.grad_norm()).abs() <= 1e-9 * plain.grad_norm());
            let clip = (step % 2 == 1).then_some(10.0); // the norm is ~1e3: clipped
            let before = b.detach().copy();
            fused.step(1e-2, clip);
            plain.step(1e-2, clip);
            moved = moved.max((&b - before).abs().max().double_value(&[]));
        }
        let differ = |x: &Tensor, y: &Tensor| (x - y).abs().max().double_value(&[]);
        assert!(moved > 5e-3, "the updates moved the weights by only {moved}");
        assert!(differ(&a, &b) <= 1e-6, "weights differ by {}", differ(&a, &b));
        assert!(differ(&fused.exp_avg["w"], &plain.exp_avg["w"]) <= 1e-6);
        assert!(differ(&fused.exp_avg_sq["w"], &plain.exp_avg_sq["w"]) <= 1e-3, "second moments of ~1e4");
    }

    #[test]
    fn state_round_trip() {
        let w = Tensor::from_slice(&[1.0f32, 2.0]).set_requires_grad(true);
        let mut opt = Adam::new([("w".to_string(), w.shallow_clone())].into());
        w.square().sum(Kind::Float).backward();
        opt.step(0.01, None);
        let mut a = Archive::new();
        opt.save_into(&mut a, "opt/");
        let w2 = Tensor::zeros([2], (Kind::Float, Device::Cpu)).set_requires_grad(true);
        let mut opt2 = Adam::new([("w".to_string(), w2)].into());
        opt2.load_from(&a, "opt/").unwrap();
        assert_eq!(opt2.steps, 1);
        assert!(opt2.exp_avg["w"].equal(&opt.exp_avg["w"]));
        assert!(opt2.exp_avg_sq["w"].equal(&opt.exp_avg_sq["w"]));
    }
}
