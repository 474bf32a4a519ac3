// Temporal conv encoder/decoder over per-frame joint vectors (MoMask-style:
// stride-2 downsampling stages with dilated residual blocks, nearest upsampling
// in the decoder). Shared by the motion autoencoder and the VQ tokenizer.
#pragma once
#include <torch/torch.h>

namespace mc {

struct ConvMotionOptions {
  int in_dim = 66;     // J*3
  int width = 256;     // channels
  int latent = 256;    // code dimension
  int down_stages = 2; // x2 each: 2 stages = x4 in time
  int res_depth = 2;   // residual blocks per stage
  int dilation_growth = 3;
};

struct ResConv1dImpl : torch::nn::Module {
  ResConv1dImpl(int channels, int dilation);
  torch::Tensor forward(const torch::Tensor& x);  // [B, C, T]
  torch::nn::Conv1d conv1{nullptr}, conv2{nullptr};
};
TORCH_MODULE(ResConv1d);

struct ConvMotionEncoderImpl : torch::nn::Module {
  explicit ConvMotionEncoderImpl(const ConvMotionOptions& o);
  torch::Tensor forward(const torch::Tensor& x);  // [B, T, in_dim] -> [B, T / 2^stages, latent]
  torch::nn::Sequential net{nullptr};
};
TORCH_MODULE(ConvMotionEncoder);

struct ConvMotionDecoderImpl : torch::nn::Module {
  explicit ConvMotionDecoderImpl(const ConvMotionOptions& o);
  torch::Tensor forward(const torch::Tensor& z);  // [B, T', latent] -> [B, T' * 2^stages, in_dim]
  torch::nn::Sequential net{nullptr};
};
TORCH_MODULE(ConvMotionDecoder);

}  // namespace mc
