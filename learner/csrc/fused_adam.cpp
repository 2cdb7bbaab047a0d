// libtorch's fused Adam kernel (`at::_fused_adam_`, what PyTorch's `Adam(fused=True)` calls),
// which tch does not wrap: one pass over each parameter's memory instead of the seven of the
// textbook update, on whatever device the tensors live (uavmeta_learner::optim).
//
// Tensors arrive as tch's handles (`torch::Tensor *`, torch-sys's `tensor`). A C++ exception
// never crosses into Rust: its message is returned (freed by `uavmeta_free_error`), null on
// success.

#include <ATen/ATen.h>
#include <ATen/core/grad_mode.h>
#include <cstdlib>
#include <cstring>
#include <vector>

namespace {
std::vector<at::Tensor> list(at::Tensor **tensors, size_t n) {
  std::vector<at::Tensor> out;
  out.reserve(n);
  for (size_t i = 0; i < n; i++) out.push_back(*tensors[i]);
  return out;
}
}  // namespace

extern "C" char *uavmeta_fused_adam(at::Tensor **params, at::Tensor **grads,
                                    at::Tensor **exp_avgs, at::Tensor **exp_avg_sqs,
                                    at::Tensor **steps, size_t n, double lr, double beta1,
                                    double beta2, double weight_decay, double eps) {
  try {
    at::NoGradGuard no_grad;
    auto step_list = list(steps, n);
    // The step count first, as torch.optim.Adam does: the kernel reads the incremented one.
    for (auto &s : step_list) s.add_(1);
    at::_fused_adam_(list(params, n), list(grads, n), list(exp_avgs, n), list(exp_avg_sqs, n),
                     /*max_exp_avg_sqs=*/{}, step_list, lr, beta1, beta2, weight_decay, eps,
                     /*amsgrad=*/false, /*maximize=*/false);
    return nullptr;
  } catch (const std::exception &e) {
    return strdup(e.what());
  }
}

extern "C" void uavmeta_free_error(char *error) { free(error); }
