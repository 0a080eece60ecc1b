//! Data-parallel training's link between processes: libtorch's own
//! distributed engine (c10d) through the small C++ shim `shim.cpp` that
//! build.rs compiles against the linked libtorch. A process started by
//! `torchrun` reads its place from torchrun's environment ([`Launch`]),
//! joins a TCPStore and a Gloo (CPU) or NCCL (CUDA) process group
//! ([`Group`]) and sums, averages or broadcasts tensors in place. No
//! collective and no launcher of flashmat's own: c10d moves the bytes,
//! torchrun starts, watches and restarts the processes.
//!
//! Collectives are matched by order: every rank must issue the same ones in
//! the same order. A rank that dies closes its sockets, so the others' next
//! collective fails at once; one that hangs makes them fail after
//! [`Config::timeout`]. Either way each gets one error line.

use anyhow::{bail, Context, Result};
use std::ffi::{c_char, c_int, c_void, CString};
use std::time::Duration;
use tch::{Device, Kind, Tensor};

extern "C" {
    fn flashmat_dist_has_nccl() -> c_int;
    #[allow(clippy::too_many_arguments)]
    fn flashmat_dist_new(
        host: *const c_char,
        port: c_int,
        rank: c_int,
        world: c_int,
        is_server: c_int,
        nccl: c_int,
        timeout_ms: i64,
        prefix: *const c_char,
        err: *mut c_char,
        err_len: usize,
    ) -> *mut c_void;
    fn flashmat_dist_free(group: *mut c_void);
    fn flashmat_dist_all_reduce_sum(group: *mut c_void, tensors: *const *mut c_void, n: usize, err: *mut c_char, err_len: usize) -> c_int;
    fn flashmat_dist_broadcast(group: *mut c_void, tensors: *const *mut c_void, n: usize, root: c_int, err: *mut c_char, err_len: usize) -> c_int;
}

/// Whether this build can make NCCL process groups (build.rs found
/// libtorch_cuda, `nccl.h` and the CUDA headers).
pub fn has_nccl() -> bool {
    // SAFETY: a constant of the shim.
    unsafe { flashmat_dist_has_nccl() != 0 }
}

/// Settings of the process group.
#[derive(Clone, Debug)]
pub struct Config {
    /// How long a collective (or joining the group) waits for the other
    /// ranks before it fails: bounds how long the others wait on a rank
    /// that hangs (one that dies is noticed at once). It must exceed what
    /// rank 0 alone spends between two steps (checkpoint, checks).
    pub timeout: Duration,
    /// Gradients are flattened into buckets of at most this many bytes,
    /// one collective each, all in flight together.
    pub bucket_bytes: usize,
}

impl Default for Config {
    fn default() -> Self {
        Self { timeout: Duration::from_secs(600), bucket_bytes: 25 << 20 }
    }
}

/// Environment variable that sets [`Config::timeout`] in seconds.
pub const TIMEOUT_ENV: &str = "FLASHMAT_DIST_TIMEOUT";

impl Config {
    /// The defaults, with the timeout from [`TIMEOUT_ENV`] when set.
    pub fn from_env() -> Result<Self> {
        let mut c = Self::default();
        if let Ok(v) = std::env::var(TIMEOUT_ENV) {
            let s: f64 = v.trim().parse().ok().filter(|s: &f64| s.is_finite() && *s > 0.0).with_context(|| format!("{TIMEOUT_ENV}={v}: give the collectives' timeout in seconds (> 0)"))?;
            c.timeout = Duration::from_secs_f64(s);
        }
        Ok(c)
    }
}

/// Where torchrun placed this process.
#[derive(Clone, Debug, PartialEq)]
pub struct Launch {
    pub rank: usize,
    pub world: usize,
    /// Rank on this node: the CUDA device it trains on.
    pub local_rank: usize,
    pub master_addr: String,
    pub master_port: u16,
    /// torchrun's agent serves the store (`TORCHELASTIC_USE_AGENT_STORE`):
    /// every rank connects as a client, as PyTorch's `env://` does.
    pub agent_store: bool,
    /// torchrun's restart count: a restarted job joins a fresh group.
    pub restart: u64,
}

impl Launch {
    /// This process's place when `WORLD_SIZE` is set (torchrun, or the same
    /// variables set by hand); `None` for a plain process.
    pub fn from_env() -> Result<Option<Self>> {
        Self::from_vars(|k| std::env::var(k).ok())
    }

    /// [`Launch::from_env`] reading variables through `var` (tests).
    pub fn from_vars(var: impl Fn(&str) -> Option<String>) -> Result<Option<Self>> {
        let Some(world) = var("WORLD_SIZE") else { return Ok(None) };
        let num = |k: &str, default: Option<&str>| -> Result<usize> {
            let v = var(k).or(default.map(String::from)).with_context(|| format!("WORLD_SIZE is set but {k} is not: start the ranks with torchrun"))?;
            v.trim().parse().with_context(|| format!("{k}={v} is not a number"))
        };
        let world: usize = world.trim().parse().with_context(|| format!("WORLD_SIZE={world} is not a number"))?;
        let rank = num("RANK", None)?;
        let local_rank = num("LOCAL_RANK", Some("0"))?;
        if world == 0 || rank >= world {
            bail!("RANK={rank} must lie below WORLD_SIZE={world}");
        }
        let master_addr = var("MASTER_ADDR").unwrap_or_else(|| "127.0.0.1".into());
        let port = num("MASTER_PORT", Some("29500"))?;
        let master_port = u16::try_from(port).ok().filter(|p| *p > 0).with_context(|| format!("MASTER_PORT={port} is not a port"))?;
        let agent_store = var("TORCHELASTIC_USE_AGENT_STORE").is_some_and(|v| v == "True");
        let restart = var("TORCHELASTIC_RESTART_COUNT").and_then(|v| v.parse().ok()).unwrap_or(0);
        Ok(Some(Self { rank, world, local_rank, master_addr, master_port, agent_store, restart }))
    }

    /// The device this rank trains on: `cuda` means this node's GPU
    /// `LOCAL_RANK`; the CPU stays the CPU.
    pub fn device_for(&self, asked: Device) -> Result<Device> {
        match asked {
            Device::Cuda(_) => {
                let n = tch::Cuda::device_count() as usize;
                anyhow::ensure!(self.local_rank < n, "LOCAL_RANK={} but this node has {n} CUDA device(s): start at most {n} processes a node (--nproc-per-node)", self.local_rank);
                Ok(Device::Cuda(self.local_rank))
            }
            other => Ok(other),
        }
    }
}

/// A joined process group: this rank's place and the c10d backend.
pub struct Group {
    handle: *mut c_void,
    pub rank: usize,
    pub world: usize,
    /// Where the collectives' tensors live (CPU for Gloo, the rank's GPU for NCCL).
    pub device: Device,
    config: Config,
    /// Nanoseconds spent in collectives since [`Group::take_seconds`].
    spent: std::sync::atomic::AtomicU64,
}

// SAFETY: the c10d backend is used from one thread at a time (the training
// loop's); it is thread-safe itself, the handle is a plain pointer to it.
unsafe impl Send for Group {}
unsafe impl Sync for Group {}

impl Drop for Group {
    fn drop(&mut self) {
        // SAFETY: made by flashmat_dist_new, freed once.
        unsafe { flashmat_dist_free(self.handle) }
    }
}

const ERR_LEN: usize = 1024;

fn error_text(buf: &[u8]) -> String {
    let end = buf.iter().position(|&b| b == 0).unwrap_or(buf.len());
    String::from_utf8_lossy(&buf[..end]).trim().to_string()
}

impl Group {
    /// Joins the group of `launch` on `device` (Gloo for the CPU, NCCL for
    /// CUDA): waits up to `config.timeout` for every rank.
    pub fn join(launch: &Launch, device: Device, config: Config) -> Result<Self> {
        let nccl = device.is_cuda();
        if nccl && !has_nccl() {
            bail!("--device cuda under torchrun needs NCCL, and this flashmat was built without it (build.rs found no nccl.h and CUDA headers beside libtorch)");
        }
        let host = CString::new(launch.master_addr.clone())?;
        // A restarted job's ranks meet under a fresh prefix of the store.
        let prefix = CString::new(format!("flashmat/attempt-{}/", launch.restart))?;
        let is_server = !launch.agent_store && launch.rank == 0;
        let mut err = vec![0u8; ERR_LEN];
        // SAFETY: valid C strings and an error buffer of the length given.
        let handle = unsafe {
            flashmat_dist_new(
                host.as_ptr(),
                launch.master_port as c_int,
                launch.rank as c_int,
                launch.world as c_int,
                is_server as c_int,
                nccl as c_int,
                config.timeout.as_millis() as i64,
                prefix.as_ptr(),
                err.as_mut_ptr() as *mut c_char,
                err.len(),
            )
        };
        if handle.is_null() {
            bail!(
                "rank {} of {} could not join the process group at {}:{} ({}): {}",
                launch.rank,
                launch.world,
                launch.master_addr,
                launch.master_port,
                if nccl { "NCCL" } else { "Gloo" },
                error_text(&err)
            );
        }
        Ok(Self { handle, rank: launch.rank, world: launch.world, device, config, spent: Default::default() })
    }

    pub fn is_leader(&self) -> bool {
        self.rank == 0
    }

    /// Seconds this rank spent in collectives (waiting for the others
    /// included) since the last call.
    pub fn take_seconds(&self) -> f64 {
        self.spent.swap(0, std::sync::atomic::Ordering::Relaxed) as f64 * 1e-9
    }

    fn count(&self, since: std::time::Instant) {
        self.spent.fetch_add(since.elapsed().as_nanos() as u64, std::sync::atomic::Ordering::Relaxed);
    }

    fn fail(&self, what: &str, err: &[u8]) -> anyhow::Error {
        anyhow::anyhow!(
            "rank {} of {}: {what} failed, another rank died or stopped answering within {} s ({}); the last checkpoint is kept",
            self.rank,
            self.world,
            self.config.timeout.as_secs(),
            error_text(err)
        )
    }

    fn pointers(tensors: &mut [Tensor]) -> Vec<*mut c_void> {
        tensors.iter_mut().map(|t| t.as_mut_ptr() as *mut c_void).collect()
    }

    /// Sums every tensor over the ranks, in place. Each must be contiguous,
    /// on [`Group::device`], and of the same shape and kind on every rank.
    pub fn all_reduce_sum(&self, tensors: &mut [Tensor]) -> Result<()> {
        if tensors.is_empty() {
            return Ok(());
        }
        let ptrs = Self::pointers(tensors);
        let mut err = vec![0u8; ERR_LEN];
        let t0 = std::time::Instant::now();
        // SAFETY: live at::Tensor pointers (tch's representation), an error buffer of its length.
        let rc = unsafe { flashmat_dist_all_reduce_sum(self.handle, ptrs.as_ptr(), ptrs.len(), err.as_mut_ptr() as *mut c_char, err.len()) };
        self.count(t0);
        if rc != 0 {
            return Err(self.fail("all-reduce", &err));
        }
        Ok(())
    }

    /// Copies rank `root`'s values of every tensor into every rank's, in place.
    pub fn broadcast(&self, tensors: &mut [Tensor], root: usize) -> Result<()> {
        if tensors.is_empty() {
            return Ok(());
        }
        let ptrs = Self::pointers(tensors);
        let mut err = vec![0u8; ERR_LEN];
        let t0 = std::time::Instant::now();
        // SAFETY: as in all_reduce_sum.
        let rc = unsafe { flashmat_dist_broadcast(self.handle, ptrs.as_ptr(), ptrs.len(), root as c_int, err.as_mut_ptr() as *mut c_char, err.len()) };
        self.count(t0);
        if rc != 0 {
            return Err(self.fail("broadcast", &err));
        }
        Ok(())
    }

    /// The element-wise sum over the ranks of a few numbers (decisions,
    /// losses), in f64.
    pub fn sum_f64(&self, values: &[f64]) -> Result<Vec<f64>> {
        let mut t = [Tensor::from_slice(values).to_device(self.device)];
        self.all_reduce_sum(&mut t)?;
        Ok(Vec::<f64>::try_from(t[0].to_device(Device::Cpu))?)
    }

    /// Waits until every rank got here.
    pub fn barrier(&self) -> Result<()> {
        self.sum_f64(&[1.0]).map(drop)
    }

    /// Averages the tensors over the ranks in place: flattened into
    /// buckets of at most [`Config::bucket_bytes`] (one collective each,
    /// all in flight together), summed, divided by the world size and
    /// copied back. `extra` (e.g. a step's flags) rides in the first bucket
    /// and comes back summed, not averaged. tensors: any shapes, f32, on
    /// [`Group::device`]; the same list on every rank.
    pub fn average(&self, tensors: &[Tensor], extra: &[f32]) -> Result<Vec<f32>> {
        let limit = (self.config.bucket_bytes / 4).max(1) as i64;
        let mut buckets: Vec<Vec<&Tensor>> = vec![vec![]];
        let mut filled = extra.len() as i64;
        for t in tensors {
            let n = t.numel() as i64;
            if filled > 0 && filled + n > limit {
                buckets.push(vec![]);
                filled = 0;
            }
            buckets.last_mut().expect("one bucket at least").push(t);
            filled += n;
        }
        let mut flat: Vec<Tensor> = buckets
            .iter()
            .enumerate()
            .map(|(i, b)| {
                let mut parts: Vec<Tensor> = b.iter().map(|t| t.detach().to_kind(Kind::Float).reshape([-1])).collect();
                if i == 0 && !extra.is_empty() {
                    parts.insert(0, Tensor::from_slice(extra).to_device(self.device));
                }
                if parts.is_empty() {
                    Tensor::zeros([0], (Kind::Float, self.device))
                } else {
                    Tensor::cat(&parts, 0)
                }
            })
            .collect();
        self.all_reduce_sum(&mut flat)?;
        let scale = 1.0 / self.world as f64;
        let mut extra_out = vec![];
        tch::no_grad(|| -> Result<()> {
            for (i, (b, f)) in buckets.iter().zip(&flat).enumerate() {
                let mut at = 0i64;
                if i == 0 && !extra.is_empty() {
                    extra_out = Vec::<f32>::try_from(f.narrow(0, 0, extra.len() as i64).to_device(Device::Cpu))?;
                    at = extra.len() as i64;
                }
                for t in b {
                    let n = t.numel() as i64;
                    let avg = f.narrow(0, at, n).view(t.size().as_slice()) * scale;
                    t.shallow_clone().copy_(&avg);
                    at += n;
                }
            }
            Ok(())
        })?;
        Ok(extra_out)
    }
}

#[cfg(test)]
mod tests;
