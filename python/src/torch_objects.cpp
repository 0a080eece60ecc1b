// torch.Tensor <-> at::Tensor without a copy: the two calls of torch's own
// Python binding (libtorch_python) that pyo3-tch makes, compiled here so
// that tch keeps its features (pyo3-tch needs tch's `python-extension`,
// which rebuilds torch-sys's C++ wrapper, tch and all of flashmat a second
// time). tch's `Tensor` owns a heap `at::Tensor*`, which these pass.
#include <torch/csrc/autograd/python_variable.h>

extern "C" {

// A new `at::Tensor*` sharing obj's storage and autograd state (the
// caller owns it: tch::Tensor::from_ptr), or null when obj is no tensor.
void* flashmat_tensor_from_py(PyObject* obj) {
  if (!THPVariable_Check(obj)) return nullptr;
  return new at::Tensor(THPVariable_Unpack(obj));
}

// A new reference to the torch.Tensor of *t (null with a Python error set
// on failure).
PyObject* flashmat_tensor_to_py(void* t) {
  try {
    return THPVariable_Wrap(*static_cast<at::Tensor*>(t));
  } catch (const std::exception& e) {
    PyErr_SetString(PyExc_RuntimeError, e.what());
    return nullptr;
  }
}

}
