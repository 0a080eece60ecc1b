//! The arithmetic the networks run in (`--precision`): full f32, TF32
//! matmuls and convolutions on a GPU, or bf16 autocast for the networks'
//! forward passes. One process-wide setting, read by every network's
//! forward ([`forward`]); the losses, their logs, the gradients' norms and
//! the optimizers stay f32 whatever it is (a forward's output comes back
//! as f32, and parameters and gradients are f32).
//!
//! tch 0.24 binds CUDA autocast only, in f16; `shim.cpp` reaches libtorch's
//! autocast for a device type and dtype, and its TF32 switches.

use anyhow::{bail, Result};
use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicU8, Ordering};
use tch::{Device, Kind, Tensor};

/// What the networks compute in.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    /// f32 everywhere (libtorch's default lets cuDNN's convolutions use
    /// TF32; this turns that off too).
    F32,
    /// TF32 for f32 matmuls and convolutions on a GPU (10-bit mantissa
    /// products, f32 sums); the CPU has no TF32 and computes f32.
    #[default]
    Tf32,
    /// bf16 autocast for every network's forward (convolutions and
    /// matmuls in bf16, normalisations and reductions as autocast
    /// chooses), TF32 for what stays f32.
    Bf16,
}

impl std::str::FromStr for Precision {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "f32" => Ok(Self::F32),
            "tf32" => Ok(Self::Tf32),
            "bf16" => Ok(Self::Bf16),
            _ => bail!("--precision must be f32, tf32 or bf16 (got '{s}')"),
        }
    }
}

impl std::fmt::Display for Precision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Self::F32 => "f32",
            Self::Tf32 => "tf32",
            Self::Bf16 => "bf16",
        })
    }
}

static MODE: AtomicU8 = AtomicU8::new(u8::MAX);

extern "C" {
    fn flashmat_autocast_enter(cuda: i32, prev_enabled: *mut i32, prev_dtype: *mut i32, err: *mut u8, n: usize) -> i32;
    fn flashmat_autocast_exit(cuda: i32, prev_enabled: i32, prev_dtype: i32, err: *mut u8, n: usize) -> i32;
    fn flashmat_set_tf32(on: i32, err: *mut u8, n: usize) -> i32;
}

/// Runs one shim call; its error message as an error.
fn call(f: impl FnOnce(*mut u8, usize) -> i32) -> Result<()> {
    let mut err = [0u8; 512];
    if f(err.as_mut_ptr(), err.len()) == 0 {
        return Ok(());
    }
    let end = err.iter().position(|&b| b == 0).unwrap_or(err.len());
    bail!("libtorch: {}", String::from_utf8_lossy(&err[..end]).lines().next().unwrap_or(""))
}

/// Sets the process's precision (libtorch's TF32 switches with it).
pub fn set(p: Precision) -> Result<()> {
    // SAFETY: the shim reads only its arguments and writes at most n bytes to err.
    call(|err, n| unsafe { flashmat_set_tf32(i32::from(p != Precision::F32), err, n) })?;
    MODE.store(p as u8, Ordering::SeqCst);
    Ok(())
}

/// The process's precision: [`Precision::default`] until [`set`].
pub fn current() -> Precision {
    match MODE.load(Ordering::SeqCst) {
        0 => Precision::F32,
        2 => Precision::Bf16,
        _ => Precision::Tf32,
    }
}

/// Runs a network's forward pass `f` on `device` in the process's
/// precision: under bf16 autocast with [`Precision::Bf16`] (the region
/// ends, and the cache of bf16 weight copies is cleared with the outermost
/// one, before this returns), as it is otherwise. Backward passes run
/// outside: each op's gradient follows the dtype its forward ran in.
pub fn forward<T>(device: Device, f: impl FnOnce() -> T) -> T {
    if current() != Precision::Bf16 {
        return f();
    }
    let cuda = i32::from(device.is_cuda());
    let (mut enabled, mut dtype) = (0, 0);
    // SAFETY: as in `set`; the two outputs are valid i32s.
    let entered = call(|err, n| unsafe { flashmat_autocast_enter(cuda, &mut enabled, &mut dtype, err, n) });
    if entered.is_err() {
        return f(); // no autocast for this device type: f32
    }
    let out = f();
    // SAFETY: as in `set`. Leaving restores what entering saved; it cannot
    // fail for a device type that entering accepted.
    let _ = call(|err, n| unsafe { flashmat_autocast_exit(cuda, enabled, dtype, err, n) });
    out
}

/// A forward's output as the losses read it: an f32 copy when autocast
/// made it bf16 (or f16), the tensor itself otherwise (an f64 model's
/// output stays f64).
pub fn to_f32(t: Tensor) -> Tensor {
    match t.kind() {
        Kind::BFloat16 | Kind::Half => t.to_kind(Kind::Float),
        _ => t,
    }
}

#[cfg(test)]
mod tests;
