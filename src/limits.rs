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

/// An error as one line: its chain of contexts, where a libtorch
/// out-of-memory (whose message carries a C++ backtrace) ends the line
/// with [`out_of_memory`]'s words and `memory_hint` (what to lower)
/// instead. The flag says whether it was one. The CLI's `error:` line and
/// the Python package's exceptions.
pub fn error_line(e: &anyhow::Error, memory_hint: &str) -> (String, bool) {
    let mut parts = Vec::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if let Some(oom) = out_of_memory(&text) {
            parts.push(format!("{oom}: {memory_hint}"));
            return (parts.join(": "), true);
        }
        parts.push(text);
    }
    (format!("{e:#}"), false)
}

/// Recognises an out-of-memory failure in a libtorch error message (a
/// `Torch(...)` error's text, or the panic of a tch method that unwrapped
/// one, with its newlines escaped) and returns it as one line: which memory
/// ran out and, where the message says, how much was asked for and free.
/// None for any other message. Callers add what to lower: that depends on
/// the command.
pub fn out_of_memory(message: &str) -> Option<String> {
    // The words after `key`, up to `words` of them, without trailing punctuation.
    let after = |key: &str, words: usize| -> Option<String> {
        let rest = &message[message.find(key)? + key.len()..];
        let w: Vec<&str> = rest.split_whitespace().take(words).map(|w| w.trim_end_matches(['.', ',', ';', ')', '"'])).collect();
        (w.len() == words && w[0].starts_with(|c: char| c.is_ascii_digit())).then(|| w.join(" "))
    };
    const GPU: [&str; 4] = ["CUDA out of memory", "CUDA error: out of memory", "CUBLAS_STATUS_ALLOC_FAILED", "CUDNN_STATUS_ALLOC_FAILED"];
    const CPU: [&str; 4] = ["DefaultCPUAllocator: not enough memory", "DefaultCPUAllocator: can't allocate memory", "std::bad_alloc", "Cannot allocate memory"];
    if GPU.iter().any(|p| message.contains(p)) {
        let mut details = Vec::new();
        if let Some(want) = after("Tried to allocate ", 2) {
            details.push(format!("tried to allocate {want}"));
        }
        match (after(" of which ", 2), after("total capacity of ", 2)) {
            (Some(free), Some(total)) => details.push(format!("{free} of the card's {total} free")),
            (Some(free), None) => details.push(format!("{free} free")),
            _ => {}
        }
        let details = if details.is_empty() { String::new() } else { format!(" ({})", details.join("; ")) };
        return Some(format!("out of GPU memory{details}"));
    }
    // oneDNN (libtorch's CPU convolutions) reports a failed allocation
    // while setting up a layer only as this (seen under a memory cap).
    if message.contains("could not create a primitive") {
        return Some("oneDNN could not create a primitive (most likely out of memory)".into());
    }
    if CPU.iter().any(|p| message.contains(p)) {
        let size = |b: f64| if b >= (1u64 << 30) as f64 { format!("{:.2} GiB", b / (1u64 << 30) as f64) } else { format!("{:.0} MiB", b / (1u64 << 20) as f64) };
        let want = after("tried to allocate ", 1).and_then(|b| b.parse::<f64>().ok()).map(|b| format!(" (tried to allocate {})", size(b)));
        return Some(format!("out of memory{}", want.unwrap_or_default()));
    }
    None
}

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

    #[test]
    fn error_lines_join_the_chain_and_end_at_an_out_of_memory() {
        let e = anyhow::anyhow!("no such file").context("cannot read p.png");
        assert_eq!(error_line(&e, "lower --size"), ("cannot read p.png: no such file".to_string(), false));
        let e = anyhow::anyhow!("DefaultCPUAllocator: not enough memory: you tried to allocate 83886080 bytes.\nframe #0: ...").context("estimating p.png");
        assert_eq!(error_line(&e, "lower size"), ("estimating p.png: out of memory (tried to allocate 80 MiB): lower size".to_string(), true));
    }

    /// libtorch's messages: a CUDA out-of-memory inside the panic of a tch
    /// method, where the newlines of its C++ backtrace are escaped (the
    /// message as libtorch 2.11's caching allocator assembles it: its
    /// pieces are the strings of `libc10_cuda.so`; no GPU here to capture
    /// one), and the CPU allocator's, captured from libtorch 2.11 under a
    /// memory cap.
    #[test]
    fn out_of_memory_messages_become_one_line() {
        let cuda = r#"called `Result::unwrap()` on an `Err` value: Torch("CUDA out of memory. Tried to allocate 64.00 GiB. GPU 0 has a total capacity of 79.19 GiB of which 62.94 GiB is free. Including non-PyTorch memory, this process has 16.24 GiB memory in use. Of the allocated memory 15.50 GiB is allocated by PyTorch, and 12.00 MiB is reserved by PyTorch but unallocated. If reserved but unallocated memory is large try setting PYTORCH_CUDA_ALLOC_CONF=expandable_segments:True to avoid fragmentation.  See documentation for Memory Management  (https://docs.pytorch.org/docs/stable/notes/cuda.html#optimizing-memory-usage-with-pytorch-cuda-alloc-conf)\nException raised from malloc at /pytorch/c10/cuda/CUDACachingAllocator.cpp:1463 (most recent call first):\nframe #0: c10::Error::Error(c10::SourceLocation, std::string) + 0x98\n")"#;
        assert_eq!(out_of_memory(cuda).unwrap(), "out of GPU memory (tried to allocate 64.00 GiB; 62.94 GiB of the card's 79.19 GiB free)");
        // The CUDA runtime's own error, without the allocator's details.
        assert_eq!(out_of_memory("CUDA error: out of memory\nCUDA kernel errors might be asynchronously reported").unwrap(), "out of GPU memory");
        let cpu = "[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate memory: you tried to allocate 2199023255552 bytes. Error code 12 (Cannot allocate memory)";
        assert_eq!(out_of_memory(cpu).unwrap(), "out of memory (tried to allocate 2048.00 GiB)");
        assert_eq!(out_of_memory("DefaultCPUAllocator: not enough memory: you tried to allocate 83886080 bytes.").unwrap(), "out of memory (tried to allocate 80 MiB)");
        // Captured from a training step under a memory cap.
        let onednn = r#"called `Result::unwrap()` on an `Err` value: Torch("could not create a primitive")"#;
        assert_eq!(out_of_memory(onednn).unwrap(), "oneDNN could not create a primitive (most likely out of memory)");
        for other in ["shape '[2, 3]' is invalid for input of size 5", "CUDA error: an illegal memory access was encountered", "", "tried to allocate 5 bytes"] {
            assert_eq!(out_of_memory(other), None, "{other}");
        }
    }
}
