// The T2M-style evaluator: a word-level BiGRU text encoder and a conv+BiGRU motion
// encoder over mc67 joint-derived features, trained contrastively on our data
// (reference-facts §5). It shares no weights with any generator's text encoder.
#pragma once
#include <Eigen/Dense>
#include <memory>
#include <string>
#include <vector>

#include "core/config.h"
#include "data/motion_set.h"
#include "data/skeleton.h"
#include "data/text_vocab.h"

namespace mc {

struct T2MEvaluatorConfig : Config {
  int word_dim = 128;
  int text_hidden = 256;
  int movement_dim = 256;
  int motion_hidden = 256;
  int embed_dim = 256;
  int max_words = 24;
  int unit_length = 4;     // motions are cropped to a multiple of this (the movement encoder's stride)
  double margin = 10.0;    // contrastive margin (T2M)
  double dropout = 0.2;
  void visit(FieldVisitor& v) override {
    v("word_dim", word_dim, "word embedding size (learned; no GloVe here)", at_least(8));
    v("text_hidden", text_hidden, "text BiGRU hidden size per direction", at_least(8));
    v("movement_dim", movement_dim, "conv movement encoder channels (time /4)", at_least(8));
    v("motion_hidden", motion_hidden, "motion BiGRU hidden size per direction", at_least(8));
    v("embed_dim", embed_dim, "shared embedding size", at_least(2));
    v("max_words", max_words, "caption length cap in tokens (incl. <sos>/<eos>)", at_least(4));
    v("unit_length", unit_length, "motion length granularity in frames", in_range(1, 16));
    v("margin", margin, "contrastive margin for negatives", positive<double>());
    v("dropout", dropout, "dropout in the movement encoder", in_range(0.0, 0.9));
  }
};

struct T2MEvaluatorNetImpl;  // defined in t2m_evaluator.cpp

// A trained evaluator loaded from its run directory (config.yaml, checkpoints/final.pt,
// outputs/vocab.txt, outputs/evaluator_meta.yaml). Embeddings are rows of Eigen matrices.
class T2MEvaluator {
 public:
  static T2MEvaluator load(const std::string& run_dir);
  Eigen::MatrixXd embed_texts(const std::vector<std::string>& captions) const;
  // Checks skeleton and fps against the evaluator's; clips shorter than
  // 2 * unit_length frames are an error.
  Eigen::MatrixXd embed_motions(const MotionSet& m, const std::string& source) const;
  const Skeleton& skeleton() const { return skeleton_; }
  double fps() const { return fps_; }
  const std::string& run_dir() const { return run_dir_; }

 private:
  std::shared_ptr<T2MEvaluatorNetImpl> net_;
  std::shared_ptr<TextVocab> vocab_;
  T2MEvaluatorConfig cfg_;
  Skeleton skeleton_;
  double fps_ = 20;
  std::string run_dir_;
};

}  // namespace mc
