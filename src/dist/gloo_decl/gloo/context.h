// Declarations only: see ../README.md. `setTimeout` is named by an inline
// member of ProcessGroupGloo that this build never emits (its vtable lives
// in libtorch_cpu).
#pragma once
#include <chrono>
namespace gloo {
class Context {
 public:
  void setTimeout(std::chrono::milliseconds timeout);
};
}
