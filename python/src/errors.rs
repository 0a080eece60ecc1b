//! Errors across the boundary: the library's errors become Python
//! exceptions carrying the CLI's one-line message (src/main.rs
//! `error_line`), and a panic (tch's methods panic on libtorch's errors)
//! becomes one too, never a crash or a Rust backtrace.

use pyo3::exceptions::{PyFileNotFoundError, PyMemoryError, PyRuntimeError, PyUserWarning, PyValueError};
use pyo3::prelude::*;
use std::panic::{catch_unwind, AssertUnwindSafe};

/// What to lower when the library runs out of memory (the CLI's
/// `memory_hint` of estimate, with the Python names).
const MEMORY_HINT: &str = "lower max_memory (M_est then runs in tiles) or size";

pub fn value_error(message: impl Into<String>) -> PyErr {
    PyValueError::new_err(message.into())
}

/// The exception for a library error: MemoryError when libtorch ran out
/// of memory, FileNotFoundError when a file is missing, else ValueError
/// (the library's errors are about its input: files, shapes, values).
pub fn to_py_err(e: &anyhow::Error) -> PyErr {
    let (line, out_of_memory) = flashmat::limits::error_line(e, MEMORY_HINT);
    // The library's missing files: an io::Error in the chain, or its own
    // words ("does not exist", an io error formatted into the line).
    let missing = e.chain().any(|c| c.downcast_ref::<std::io::Error>().is_some_and(|io| io.kind() == std::io::ErrorKind::NotFound))
        || line.contains("does not exist")
        || line.contains("(os error 2)");
    if out_of_memory {
        PyMemoryError::new_err(line)
    } else if missing {
        PyFileNotFoundError::new_err(line)
    } else {
        PyValueError::new_err(line)
    }
}

/// libtorch's (thread-local) grad mode, put back when dropped: tch's
/// `no_grad` does not restore it when its closure panics, and Python's
/// `torch.no_grad` and autograd share it.
struct GradModeKept(i32);

impl GradModeKept {
    fn new() -> Self {
        // SAFETY: at_grad_set_enabled sets the flag and returns the old one;
        // setting it straight back leaves it as it was.
        let was = unsafe { torch_sys::at_grad_set_enabled(1) };
        unsafe { torch_sys::at_grad_set_enabled(was) };
        Self(was)
    }
}

impl Drop for GradModeKept {
    fn drop(&mut self) {
        // SAFETY: as above.
        unsafe { torch_sys::at_grad_set_enabled(self.0) };
    }
}

/// Runs `f`, turning its error or its panic into a Python exception.
pub fn guarded<T>(f: impl FnOnce() -> anyhow::Result<T>) -> PyResult<T> {
    let _grad_mode = GradModeKept::new();
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(to_py_err(&e)),
        Err(payload) => {
            let msg = payload
                .downcast_ref::<String>()
                .cloned()
                .or_else(|| payload.downcast_ref::<&str>().map(|s| s.to_string()))
                .unwrap_or_default();
            if let Some(oom) = flashmat::limits::out_of_memory(&msg) {
                return Err(PyMemoryError::new_err(format!("{oom}: {MEMORY_HINT}")));
            }
            Err(PyRuntimeError::new_err(format!("internal error: {}", panic_line(&msg))))
        }
    }
}

/// The first line of a panic's message: tch's `Torch("...")` errors come
/// with libtorch's C++ backtrace after an escaped newline.
fn panic_line(msg: &str) -> String {
    let msg = msg.replace("\\n", "\n");
    let first = msg.lines().next().unwrap_or("");
    let first = first.strip_prefix("called `Result::unwrap()` on an `Err` value: ").unwrap_or(first);
    first.strip_prefix("Torch(\"").unwrap_or(first).to_string()
}

/// Panics in this extension are caught (`guarded`) and raised with their
/// message: the default hook's lines and backtrace on stderr would be
/// noise on top.
pub fn quiet_panics() {
    std::panic::set_hook(Box::new(|_| {}));
}

/// A Python `UserWarning` (the CLI prints these as `warning: ...`).
pub fn warn(py: Python<'_>, message: &str) -> PyResult<()> {
    let category = py.get_type::<PyUserWarning>();
    let text = std::ffi::CString::new(message.replace('\0', " ")).expect("NULs were replaced");
    PyErr::warn(py, &category, &text, 1)
}

/// Runs `f` with the GIL released. libtorch's autograd engine, once
/// torch's Python binding is loaded, refuses to run backward under the GIL
/// (the refinement and the fits do); `f` touches no Python object.
pub fn without_gil<T>(py: Python<'_>, f: impl FnOnce() -> T) -> T {
    struct OnThisThread<F>(F);
    // SAFETY: allow_threads runs the closure on this same thread and hands
    // its result back there; Send is asked only so that no Python object
    // crosses, and neither `f` nor its result holds one (tensors and
    // materials only).
    unsafe impl<F> Send for OnThisThread<F> {}
    let job = OnThisThread(f);
    let out = py.allow_threads(move || {
        let job = job;
        OnThisThread((job.0)())
    });
    out.0
}
