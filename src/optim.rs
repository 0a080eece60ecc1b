//! Adam written out with tensors so that its moment estimates can be saved
//! in checkpoints (tch's built-in optimizer does not expose its state) and a
//! resumed run continues bit-for-bit.
//!
//! Three ways to run the same update: on the CPU one pass of Rust over each
//! parameter's buffers (`fused`); on a GPU over one flat buffer per network
//! ([`Flat`]: every parameter and both moments are views of it, so an update
//! is a handful of kernels and no read-back, where the per-parameter tensor
//! operations launch about ten kernels and read the gradient norm back once
//! per parameter); and the per-parameter tensor operations (the reference).

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

/// One network's parameters and moments in three flat buffers `[P]` (P the
/// number of parameters), each variable and each moment a view of its span:
/// the device path's update reads and writes them whole.
struct Flat {
    params: Tensor,
    m: Tensor,
    v: Tensor,
}

impl Flat {
    /// Moves `params` (sorted by name) into one buffer: each variable keeps
    /// its identity (the model's layers and the var store see the same
    /// tensor) and its values, and becomes a view of the buffer. Returns the
    /// buffers and the moments' per-variable views, zero.
    fn adopt(params: &BTreeMap<String, Tensor>) -> (Self, BTreeMap<String, Tensor>, BTreeMap<String, Tensor>) {
        tch::no_grad(|| {
            let flat = Tensor::cat(&params.values().map(|p| p.detach().reshape([-1])).collect::<Vec<_>>(), 0);
            let (m, v) = (flat.zeros_like(), flat.zeros_like());
            let (mut exp_avg, mut exp_avg_sq) = (BTreeMap::new(), BTreeMap::new());
            let mut offset = 0;
            for (name, p) in params {
                let (n, size) = (p.numel() as i64, p.size());
                p.shallow_clone().set_data(&flat.narrow(0, offset, n).view(size.as_slice()));
                exp_avg.insert(name.clone(), m.narrow(0, offset, n).view(size.as_slice()));
                exp_avg_sq.insert(name.clone(), v.narrow(0, offset, n).view(size.as_slice()));
                offset += n;
            }
            (Self { params: flat, m, v }, exp_avg, exp_avg_sq)
        })
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
    /// The flat buffers of the device path (parameters on a GPU, or
    /// [`Adam::new_flat`]).
    flat: Option<Flat>,
}

impl Adam {
    /// params: the trainable variables of one network (name -> tensor).
    /// f32 parameters on a GPU are moved into flat buffers ([`Flat`]).
    pub fn new(params: HashMap<String, Tensor>) -> Self {
        let on_gpu = !params.is_empty() && params.values().all(|p| p.device().is_cuda() && p.kind() == tch::Kind::Float);
        Self::with_layout(params, on_gpu)
    }

    /// The device path's flat buffers wherever the parameters are (the CPU
    /// tests prove it with it).
    pub fn new_flat(params: HashMap<String, Tensor>) -> Self {
        Self::with_layout(params, true)
    }

    fn with_layout(params: HashMap<String, Tensor>, flat: bool) -> Self {
        let params: BTreeMap<String, Tensor> = params.into_iter().filter(|(_, t)| t.requires_grad()).collect();
        let (flat, exp_avg, exp_avg_sq) = if flat && !params.is_empty() {
            let (flat, m, v) = Flat::adopt(&params);
            (Some(flat), m, v)
        } else {
            let zeros = || params.iter().map(|(k, v)| (k.clone(), v.zeros_like())).collect();
            (None, zeros(), zeros())
        };
        Self { params, exp_avg, exp_avg_sq, beta1: 0.9, beta2: 0.999, eps: 1e-8, steps: 0, fused: true, flat }
    }

    /// The gradients in one flat tensor `[P]` (the parameters' order of
    /// [`Flat`]), on the device path with every gradient defined; None
    /// otherwise (a variable outside the loss keeps today's per-parameter
    /// update, which skips it).
    fn flat_grad(&self) -> Option<Tensor> {
        if self.flat.is_none() || !self.fused {
            return None;
        }
        let grads: Vec<Tensor> = self.params.values().map(|p| p.grad()).collect();
        grads.iter().all(Tensor::defined).then(|| Tensor::cat(&grads.iter().map(|g| g.reshape([-1])).collect::<Vec<_>>(), 0))
    }

    /// The global L2 norm of the gradients as a 0-dim f64 tensor on their
    /// device (no read-back: a training step reads it with its losses).
    pub fn grad_norm_tensor(&self) -> Tensor {
        if let Some(g) = self.flat_grad() {
            return g.square().sum(tch::Kind::Double).sqrt();
        }
        if self.fused && self.params.values().all(|p| p.device() == tch::Device::Cpu) {
            return Tensor::from(self.grad_norm()); // the host's sum: nothing to wait for
        }
        let device = self.params.values().next().map_or(tch::Device::Cpu, Tensor::device);
        let squares: Vec<Tensor> = self.params.values().map(|p| p.grad()).filter(Tensor::defined).map(|g| g.square().sum(tch::Kind::Double)).collect();
        match squares.is_empty() {
            true => Tensor::zeros([], (tch::Kind::Double, device)),
            false => Tensor::stack(&squares, 0).sum(tch::Kind::Double).sqrt(),
        }
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
        if let Some(g) = self.flat_grad() {
            return g.square().sum(tch::Kind::Double).sqrt().double_value(&[]);
        }
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
        if let Some(g) = self.flat_grad() {
            return self.flat_step(g, lr, clip);
        }
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

    /// [`Adam::step`] on the flat buffers: the tensor update's operations in
    /// its order over all parameters at once, the clipping scale computed
    /// on the device (min(1, clip / norm) equals the host's choice between
    /// 1 and clip / norm).
    /// g: the flat gradients `[P]`.
    fn flat_step(&mut self, g: Tensor, lr: f64, clip: Option<f64>) {
        self.steps += 1;
        let (b1, b2) = (self.beta1, self.beta2);
        let bc1 = 1.0 - b1.powi(self.steps as i32);
        let bc2 = 1.0 - b2.powi(self.steps as i32);
        let flat = self.flat.as_ref().expect("flat_grad is Some only with flat buffers");
        tch::no_grad(|| {
            let g = match clip {
                Some(max) => {
                    let norm = g.square().sum(tch::Kind::Double).sqrt();
                    let scale = (Tensor::full([], max, (tch::Kind::Double, g.device())) / (norm + 1e-12)).clamp_max(1.0).to_kind(tch::Kind::Float);
                    g * scale
                }
                None => g,
            };
            let (mut m, mut v) = (flat.m.shallow_clone(), flat.v.shallow_clone());
            let _ = m.g_mul_scalar_(b1).g_add_(&(&g * (1.0 - b1)));
            let _ = v.g_mul_scalar_(b2).g_add_(&(g.square() * (1.0 - b2)));
            let denom = (&v / bc2).sqrt() + self.eps;
            let update = (&m / bc1) / denom * lr;
            let _ = flat.params.shallow_clone().g_sub_(&update);
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

    /// Three variables of a network under the flat device path and under
    /// the per-parameter tensor operations, over steps with and without
    /// clipping: the same weights and moments to f32 rounding, the
    /// variables still the network's own (a forward through the original
    /// handles sees the update), and the flat norm equal to the host's.
    #[test]
    fn flat_update_matches_the_tensor_update() {
        let shapes: [&[i64]; 3] = [&[4, 3, 3, 3], &[4], &[7, 5]];
        let make = || -> Vec<Tensor> {
            tch::manual_seed(3);
            shapes.iter().map(|s| Tensor::randn(*s, (Kind::Float, Device::Cpu)).set_requires_grad(true)).collect()
        };
        let (a, b) = (make(), make());
        let named = |v: &[Tensor]| v.iter().enumerate().map(|(i, t)| (format!("w{i}"), t.shallow_clone())).collect::<HashMap<_, _>>();
        let mut flat = Adam::new_flat(named(&a));
        let mut plain = Adam::new(named(&b));
        plain.fused = false;
        assert!(flat.flat.is_some() && plain.flat.is_none());
        let loss = |v: &[Tensor], step: i64| -> Tensor {
            let x = Tensor::ones([1, 3, 6, 6], (Kind::Float, Device::Cpu)) * (step + 1) as f64;
            let y = x.conv2d(&v[0], Some(&v[1]), [1, 1], [0, 0], [1, 1], 1).sum(Kind::Float);
            y + (&v[2] * &v[2]).sum(Kind::Float) * 3.0
        };
        for step in 0..5 {
            for (v, opt) in [(&a, &mut flat), (&b, &mut plain)] {
                opt.zero_grad();
                loss(v, step).backward();
            }
            let (nf, np) = (flat.grad_norm(), plain.grad_norm());
            assert!((nf - np).abs() <= 1e-9 * np, "{nf} against {np}");
            assert!((flat.grad_norm_tensor().double_value(&[]) - np).abs() <= 1e-9 * np);
            let clip = (step % 2 == 1).then_some(0.5 * np); // clipped to half its norm
            flat.step(1e-2, clip);
            plain.step(1e-2, clip);
        }
        for (i, (x, y)) in a.iter().zip(&b).enumerate() {
            let d = (x - y).abs().max().double_value(&[]);
            assert!(d <= 1e-6, "w{i} differs by {d}");
            let moved = (x - &make()[i]).abs().max().double_value(&[]);
            assert!(moved > 1e-2, "w{i} moved by only {moved}");
            let name = format!("w{i}");
            assert!((&flat.exp_avg[&name] - &plain.exp_avg[&name]).abs().max().double_value(&[]) <= 1e-6);
        }
        // The variables are views of the one buffer that the update wrote.
        let total: i64 = a.iter().map(|t| t.numel() as i64).sum();
        let buffer = &flat.flat.as_ref().unwrap().params;
        assert_eq!(buffer.size(), [total]);
        assert!(buffer.narrow(0, 0, 108).view([4, 3, 3, 3]).equal(&a[0].detach()));
    }

    /// A variable without a gradient (outside the loss) takes the
    /// per-parameter path, which leaves it and its moments untouched.
    #[test]
    fn flat_update_skips_a_variable_without_gradient() {
        let used = Tensor::from_slice(&[1.0f32, 2.0]).set_requires_grad(true);
        let unused = Tensor::from_slice(&[5.0f32]).set_requires_grad(true);
        let mut opt = Adam::new_flat([("a".to_string(), used.shallow_clone()), ("b".to_string(), unused.shallow_clone())].into());
        used.square().sum(Kind::Float).backward();
        assert!(opt.flat_grad().is_none());
        opt.step(0.1, Some(1.0));
        assert_eq!(Vec::<f32>::try_from(unused.detach()).unwrap(), [5.0]);
        let got: Vec<f32> = Vec::try_from(used.detach()).unwrap();
        assert!((got[0] - 0.9).abs() < 1e-6 && (got[1] - 1.9).abs() < 1e-6, "{got:?}");
        assert_eq!(opt.exp_avg_sq["b"].double_value(&[0]), 0.0);
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
