// The few libtorch switches tch 0.24 does not bind: autocast's device and
// dtype (tch only turns CUDA autocast on, in f16) and TF32 matmuls. Every
// function returns 0, or -1 with the exception's message in `err`.
#include <ATen/Context.h>
#include <ATen/autocast_mode.h>

#include <cstring>
#include <exception>

namespace {

void put(char* err, size_t n, const char* msg) {
  if (n == 0) return;
  std::strncpy(err, msg, n - 1);
  err[n - 1] = '\0';
}

at::DeviceType device_type(int cuda) { return cuda ? at::kCUDA : at::kCPU; }

}  // namespace

extern "C" {

// Enters a bf16 autocast region on the CPU (cuda = 0) or CUDA: saves the
// previous switch and dtype in prev_enabled / prev_dtype.
int flashmat_autocast_enter(int cuda, int* prev_enabled, int* prev_dtype, char* err, size_t n) {
  try {
    auto dev = device_type(cuda);
    *prev_enabled = at::autocast::is_autocast_enabled(dev) ? 1 : 0;
    *prev_dtype = static_cast<int>(at::autocast::get_autocast_dtype(dev));
    at::autocast::set_autocast_dtype(dev, at::kBFloat16);
    at::autocast::set_autocast_enabled(dev, true);
    at::autocast::increment_nesting();
    return 0;
  } catch (const std::exception& e) {
    put(err, n, e.what());
    return -1;
  }
}

// Leaves the region: the saved state back, and the cache of bf16 weight
// copies cleared when the outermost region ends (a stale copy would
// outlive the optimizer's update).
int flashmat_autocast_exit(int cuda, int prev_enabled, int prev_dtype, char* err, size_t n) {
  try {
    auto dev = device_type(cuda);
    at::autocast::set_autocast_enabled(dev, prev_enabled != 0);
    at::autocast::set_autocast_dtype(dev, static_cast<at::ScalarType>(prev_dtype));
    if (at::autocast::decrement_nesting() == 0) at::autocast::clear_cache();
    return 0;
  } catch (const std::exception& e) {
    put(err, n, e.what());
    return -1;
  }
}

// TF32 for float32 matmuls (cuBLAS) and convolutions (cuDNN): on = 1,
// off = 0 (full float32). The CUDA switches only: the generic
// setFloat32MatmulPrecision("high") also lets oneDNN run the CPU's f32
// matmuls in reduced precision, which a CPU without bf16 units emulates
// (a CPU training step went 4x slower).
int flashmat_set_tf32(int on, char* err, size_t n) {
  try {
    at::globalContext().setAllowTF32CuBLAS(on != 0);
    at::globalContext().setAllowTF32CuDNN(on != 0);
    return 0;
  } catch (const std::exception& e) {
    put(err, n, e.what());
    return -1;
  }
}

}  // extern "C"
