//! torch.Tensor <-> tch::Tensor, sharing memory (src/torch_objects.cpp),
//! and photos given as pixels.

use anyhow::{bail, ensure, Result};
use flashmat::image::Image;
use flashmat::infer::{PhotoOptions, PreparedPhoto};
use pyo3::exceptions::PyTypeError;
use pyo3::prelude::*;
use std::ffi::c_void;
use tch::{Kind, Tensor};

extern "C" {
    fn flashmat_tensor_from_py(obj: *mut pyo3::ffi::PyObject) -> *mut c_void;
    fn flashmat_tensor_to_py(t: *mut c_void) -> *mut pyo3::ffi::PyObject;
}

/// A tensor that crosses the boundary as the same storage and autograd
/// state on both sides.
pub struct PyTensor(pub Tensor);

impl std::ops::Deref for PyTensor {
    type Target = Tensor;
    fn deref(&self) -> &Tensor {
        &self.0
    }
}

impl<'py> FromPyObject<'py> for PyTensor {
    fn extract_bound(ob: &Bound<'py, PyAny>) -> PyResult<Self> {
        // SAFETY: ob is a live object (the GIL is held); the shim returns a
        // new heap at::Tensor, which tch's Tensor owns and frees.
        let ptr = unsafe { flashmat_tensor_from_py(ob.as_ptr()) };
        if ptr.is_null() {
            return Err(PyTypeError::new_err(format!("expected a torch.Tensor, got {}", ob.get_type().name()?)));
        }
        Ok(PyTensor(unsafe { Tensor::from_ptr(ptr as *mut _) }))
    }
}

impl<'py> IntoPyObject<'py> for PyTensor {
    type Target = PyAny;
    type Output = Bound<'py, PyAny>;
    type Error = PyErr;

    fn into_pyobject(self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        // SAFETY: self.0 owns a valid at::Tensor for the call; the result
        // is a new reference (or null with a Python error set).
        let obj = unsafe { flashmat_tensor_to_py(self.0.as_ptr() as *mut c_void) };
        if obj.is_null() {
            return Err(PyErr::fetch(py));
        }
        Ok(unsafe { Bound::from_owned_ptr(py, obj) })
    }
}

/// `obj` as a tensor: itself, or `torch.as_tensor(obj)` (numpy arrays
/// share their memory).
pub fn as_tensor(obj: &Bound<'_, PyAny>) -> PyResult<PyTensor> {
    if let Ok(t) = obj.extract::<PyTensor>() {
        return Ok(t);
    }
    let torch = obj.py().import("torch")?;
    torch
        .call_method1("as_tensor", (obj,))
        .map_err(|_| PyTypeError::new_err(format!("photo must be a path, a torch tensor or an array, got {}", obj.get_type().name().map(|n| n.to_string()).unwrap_or_default())))?
        .extract()
}

/// A photo given as pixels, ready for M_est: `[3, H, W]` or `[H, W, 3]`
/// (4 channels: RGBA, alpha ignored with a warning); uint8 holds sRGB
/// codes, floats need `encoding` ("srgb": display values in [0, 1];
/// "linear": linear radiance, HDR allowed). No EXIF: the field of view is
/// `opts.fov_deg` or the model's own.
pub fn prepare_pixels(pixels: &Tensor, encoding: Option<&str>, opts: &PhotoOptions) -> Result<PreparedPhoto> {
    let s = pixels.size();
    ensure!(s.len() == 3, "a photo must be [3, H, W] or [H, W, 3], got {s:?}");
    let chw = match (s[0], s[2]) {
        (3 | 4, _) => pixels.shallow_clone(),
        (_, 3 | 4) => pixels.permute([2, 0, 1]),
        _ => bail!("a photo must be [3, H, W] or [H, W, 3] (or 4 channels, RGBA), got {s:?}"),
    };
    let float = |t: &Tensor| t.to_device(tch::Device::Cpu).to_kind(Kind::Float).contiguous();
    let (values, ldr) = match (pixels.kind(), encoding) {
        (Kind::Uint8, None | Some("srgb")) => (float(&chw) / 255.0, true),
        (Kind::Uint8, Some(e)) => bail!("uint8 pixels are sRGB codes; encoding '{e}' is for float pixels"),
        (Kind::Half | Kind::BFloat16 | Kind::Float | Kind::Double, Some(e @ ("srgb" | "linear"))) => (float(&chw), e == "srgb"),
        (Kind::Half | Kind::BFloat16 | Kind::Float | Kind::Double, None) => {
            bail!("float pixels need encoding='srgb' (display values in [0, 1]) or encoding='linear' (linear radiance)")
        }
        (_, Some(e)) if e != "srgb" && e != "linear" => bail!("encoding must be 'srgb' or 'linear', got '{e}'"),
        (k, _) => bail!("photo pixels must be uint8 or floats, got {k:?}"),
    };
    ensure!(flashmat::image::all_finite(&values), "the photo holds NaN or infinite values");
    if ldr {
        let max = values.max().double_value(&[]);
        ensure!(max <= 1.0, "sRGB pixels lie in [0, 1], this photo reaches {max}: say encoding='linear' for HDR radiance");
    }
    let rgb = Image::from_tensor(&values.narrow(0, 0, 3))?;
    let alpha = match values.size()[0] {
        4 => Some(Vec::<f32>::try_from(values.get(3).flatten(0, -1))?),
        _ => None,
    };
    let camera = flashmat::infer::camera::CameraInfo { orientation: 1, ..Default::default() };
    flashmat::infer::prepare_decoded(rgb, alpha.as_deref(), ldr, &camera, opts, "photo", "pixels")
}
