// Test helper for the prior health tests: a tiny T2M evaluator config (20 steps,
// width 16) on a given motion file, writing its run under `runs_root`.
#pragma once
#include <fstream>
#include <string>

namespace mc::test {

inline void write_tiny_evaluator_config(const std::string& path, const std::string& data,
                                        const std::string& runs_root) {
  std::ofstream(path)
      << "run: {experiment: evaluator, name: tiny, seed: 7, log_every: 10, checkpoint_every: 20, threads: 1, root: "
      << runs_root << "}\n"
      << "data: {path: " << data << ", fixture: '', window: 0}\n"
      << "model: {type: t2m_evaluator, word_dim: 16, text_hidden: 16, movement_dim: 16, motion_hidden: 16, "
         "embed_dim: 16, max_words: 24, margin: 10.0, dropout: 0.0}\n"
      << "optim: {steps: 20, batch_size: 16, lr: 1.0e-3, warmup: 2, schedule: cosine, min_lr_ratio: 0.1, "
         "grad_clip: 1.0, ema_decay: 0.0}\n";
}

}  // namespace mc::test
