// The C interface to libtorch's distributed engine (c10d) that src/dist
// calls: a TCPStore, a Gloo (CPU) or NCCL (CUDA) process group, in-place
// all-reduce (sum) and broadcast of tensors. tch passes tensors as
// `at::Tensor*` (torch-sys's `tensor` type). Every function catches what
// c10d throws and hands back one line of text instead: an exception
// crossing into Rust would abort the process.

#include <torch/csrc/distributed/c10d/PrefixStore.hpp>
#include <torch/csrc/distributed/c10d/ProcessGroupGloo.hpp>
#include <torch/csrc/distributed/c10d/TCPStore.hpp>
#ifdef FLASHMAT_NCCL
#include <torch/csrc/distributed/c10d/ProcessGroupNCCL.hpp>
#endif

#include <cstring>
#include <string>
#include <vector>

namespace {

struct Group {
  c10::intrusive_ptr<c10d::Store> store;
  c10::intrusive_ptr<c10d::Backend> backend;
  std::chrono::milliseconds timeout;
};

// The first line of an exception's message, without c10's backtrace.
void set_error(char* err, size_t len, const std::exception& e) {
  std::string msg;
  if (auto* c10_error = dynamic_cast<const c10::Error*>(&e)) {
    msg = c10_error->what_without_backtrace();
  } else {
    msg = e.what();
  }
  auto nl = msg.find('\n');
  if (nl != std::string::npos) msg.resize(nl);
  if (len == 0) return;
  std::strncpy(err, msg.c_str(), len - 1);
  err[len - 1] = '\0';
}

void set_error(char* err, size_t len, const char* msg) {
  if (len == 0) return;
  std::strncpy(err, msg, len - 1);
  err[len - 1] = '\0';
}

// Waits for every work item; the first failure is rethrown after all
// were waited for, so no collective is left running on a freed tensor.
void wait_all(std::vector<c10::intrusive_ptr<c10d::Work>>& works, std::chrono::milliseconds timeout) {
  std::exception_ptr first;
  for (auto& w : works) {
    try {
      if (!w->wait(timeout)) throw std::runtime_error("collective timed out");
    } catch (...) {
      if (!first) first = std::current_exception();
    }
  }
  if (first) std::rethrow_exception(first);
}

}  // namespace

extern "C" {

// 1 when this build can make NCCL process groups.
int flashmat_dist_has_nccl() {
#ifdef FLASHMAT_NCCL
  return 1;
#else
  return 0;
#endif
}

// Joins the group: the store at host:port (served by this process when
// `is_server`, else by rank 0 or torchrun's agent), under `prefix`, then
// a Gloo (`nccl` = 0) or NCCL process group of `world` ranks. Returns the
// group, or null with `err` set.
void* flashmat_dist_new(const char* host, int port, int rank, int world, int is_server, int nccl, int64_t timeout_ms, const char* prefix,
                        char* err, size_t err_len) {
  try {
    auto timeout = std::chrono::milliseconds(timeout_ms);
    c10d::TCPStoreOptions opts;
    opts.port = static_cast<std::uint16_t>(port);
    opts.isServer = is_server != 0;
    opts.numWorkers = world;
    opts.waitWorkers = false;
    opts.timeout = timeout;
    opts.multiTenant = true;
    auto tcp = c10::make_intrusive<c10d::TCPStore>(std::string(host), opts);
    c10::intrusive_ptr<c10d::Store> store = c10::make_intrusive<c10d::PrefixStore>(std::string(prefix), tcp);
    c10::intrusive_ptr<c10d::Backend> backend;
    if (nccl) {
#ifdef FLASHMAT_NCCL
      auto o = c10d::ProcessGroupNCCL::Options::create();
      o->timeout = timeout;
      backend = c10::make_intrusive<c10d::ProcessGroupNCCL>(store, rank, world, o);
#else
      set_error(err, err_len, "this flashmat was built without NCCL (build.rs found no libtorch_cuda, nccl.h and CUDA headers)");
      return nullptr;
#endif
    } else {
      auto o = c10d::ProcessGroupGloo::Options::create_default(timeout);
      o->timeout = timeout;
      backend = c10::make_intrusive<c10d::ProcessGroupGloo>(store, rank, world, o);
    }
    return new Group{store, backend, timeout};
  } catch (const std::exception& e) {
    set_error(err, err_len, e);
    return nullptr;
  }
}

void flashmat_dist_free(void* group) { delete static_cast<Group*>(group); }

// Sums each of the `n` tensors over the ranks, in place. One collective
// per tensor (Gloo reduces a list of tensors into one), all issued before
// the first is waited for, so the buckets stream back to back.
int flashmat_dist_all_reduce_sum(void* group, at::Tensor** tensors, size_t n, char* err, size_t err_len) {
  auto* g = static_cast<Group*>(group);
  try {
    std::vector<c10::intrusive_ptr<c10d::Work>> works;
    for (size_t i = 0; i < n; ++i) {
      std::vector<at::Tensor> one{*tensors[i]};
      c10d::AllreduceOptions o;
      o.reduceOp = c10d::ReduceOp::SUM;
      o.timeout = g->timeout;
      works.push_back(g->backend->allreduce(one, o));
    }
    wait_all(works, g->timeout);
    return 0;
  } catch (const std::exception& e) {
    set_error(err, err_len, e);
    return 1;
  }
}

// Copies rank `root`'s values of each tensor into every rank's, in place.
int flashmat_dist_broadcast(void* group, at::Tensor** tensors, size_t n, int root, char* err, size_t err_len) {
  auto* g = static_cast<Group*>(group);
  try {
    std::vector<c10::intrusive_ptr<c10d::Work>> works;
    for (size_t i = 0; i < n; ++i) {
      std::vector<at::Tensor> one{*tensors[i]};
      c10d::BroadcastOptions o;
      o.rootRank = root;
      o.rootTensor = 0;
      o.timeout = g->timeout;
      works.push_back(g->backend->broadcast(one, o));
    }
    wait_all(works, g->timeout);
    return 0;
  } catch (const std::exception& e) {
    set_error(err, err_len, e);
    return 1;
  }
}

}  // extern "C"
