//! A process-wide switch back to the code paths that faster ones replaced
//! with the same results to float rounding (the direction encoding's
//! tensor operations, LPIPS's one pass over both images), so `bench train`
//! can time today's step against the one it replaced in one run
//! (`train::Trainer::use_reference_step` switches the trainer's own).

use std::sync::atomic::{AtomicBool, Ordering};

static ON: AtomicBool = AtomicBool::new(false);

/// Whether the replaced code paths run.
pub fn on() -> bool {
    ON.load(Ordering::Relaxed)
}

/// Runs `f` with the replaced code paths, then restores the switch.
pub fn with<T>(f: impl FnOnce() -> T) -> T {
    let before = ON.swap(true, Ordering::Relaxed);
    let out = f();
    ON.store(before, Ordering::Relaxed);
    out
}
