// Temporal conv encoder/decoder (see conv_motion.h).
#include "models/conv_motion.h"

namespace mc {
namespace nn = torch::nn;

ResConv1dImpl::ResConv1dImpl(int c, int dilation) {
  conv1 = register_module("conv1", nn::Conv1d(nn::Conv1dOptions(c, c, 3).padding(dilation).dilation(dilation)));
  conv2 = register_module("conv2", nn::Conv1d(nn::Conv1dOptions(c, c, 1)));
}

torch::Tensor ResConv1dImpl::forward(const torch::Tensor& x) {
  return x + conv2(torch::relu(conv1(torch::relu(x))));
}

static void add_res_stack(nn::Sequential& s, const ConvMotionOptions& o, bool reverse) {
  std::vector<int> dil;
  for (int d = 0, r = 1; d < o.res_depth; ++d, r *= o.dilation_growth) dil.push_back(r);
  if (reverse) std::reverse(dil.begin(), dil.end());
  for (int r : dil) s->push_back(ResConv1d(o.width, r));
}

ConvMotionEncoderImpl::ConvMotionEncoderImpl(const ConvMotionOptions& o) {
  nn::Sequential s;
  s->push_back(nn::Conv1d(nn::Conv1dOptions(o.in_dim, o.width, 3).padding(1)));
  s->push_back(nn::Functional(torch::relu));
  for (int i = 0; i < o.down_stages; ++i) {
    s->push_back(nn::Conv1d(nn::Conv1dOptions(o.width, o.width, 4).stride(2).padding(1)));
    add_res_stack(s, o, false);
  }
  s->push_back(nn::Conv1d(nn::Conv1dOptions(o.width, o.latent, 3).padding(1)));
  net = register_module("net", s);
}

torch::Tensor ConvMotionEncoderImpl::forward(const torch::Tensor& x) {
  return net->forward(x.transpose(1, 2)).transpose(1, 2);
}

ConvMotionDecoderImpl::ConvMotionDecoderImpl(const ConvMotionOptions& o) {
  nn::Sequential s;
  s->push_back(nn::Conv1d(nn::Conv1dOptions(o.latent, o.width, 3).padding(1)));
  s->push_back(nn::Functional(torch::relu));
  for (int i = 0; i < o.down_stages; ++i) {
    add_res_stack(s, o, true);
    s->push_back(nn::Upsample(nn::UpsampleOptions().scale_factor(std::vector<double>{2.0}).mode(torch::kNearest)));
    s->push_back(nn::Conv1d(nn::Conv1dOptions(o.width, o.width, 3).padding(1)));
  }
  s->push_back(nn::Conv1d(nn::Conv1dOptions(o.width, o.width, 3).padding(1)));
  s->push_back(nn::Functional(torch::relu));
  s->push_back(nn::Conv1d(nn::Conv1dOptions(o.width, o.in_dim, 3).padding(1)));
  net = register_module("net", s);
}

torch::Tensor ConvMotionDecoderImpl::forward(const torch::Tensor& z) {
  return net->forward(z.transpose(1, 2)).transpose(1, 2);
}

}  // namespace mc
