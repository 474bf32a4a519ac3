// Word-level caption tokenizer: a vocabulary built from the training captions,
// stored in MotionSet::vocab (words in id order, specials first).
#pragma once
#include <string>
#include <unordered_map>
#include <vector>

#include "data/motion_set.h"

namespace mc {

// Lowercases ASCII letters and splits on every byte that is not a letter, so
// digits, punctuation and apostrophes separate words ("don't" -> "don", "t").
// Bytes >= 0x80 (UTF-8 multi-byte characters) count as letters and are kept as
// they are, so "café" stays one word (only ASCII is lowercased).
std::vector<std::string> tokenize_caption(const std::string& caption);

class TextVocab {
 public:
  static constexpr int kPad = 0, kUnk = 1, kSos = 2, kEos = 3;
  static const std::vector<std::string>& special_tokens();  // {"<pad>", "<unk>", "<sos>", "<eos>"}

  // Specials, then the words seen at least `min_count` times, most frequent first,
  // ties alphabetical (byte order).
  static TextVocab build(const std::vector<std::string>& captions, int min_count = 1);
  // From every caption of the clips of `split` in `m`.
  static TextVocab build(const MotionSet& m, const std::string& split = "train", int min_count = 1);

  // From a stored word list (MotionSet::vocab); UserError unless it starts with
  // the four specials and has no duplicates.
  explicit TextVocab(std::vector<std::string> words, const std::string& source = "vocab");

  struct Encoded {
    std::vector<int> ids;  // max_len ids: <sos> words... <eos> then <pad>
    int length = 0;        // ids before the padding (words + 2)
  };
  // Words past max_len - 2 are dropped so <eos> always fits; unknown words map to <unk>.
  Encoded encode(const std::string& caption, int max_len) const;
  // Words of the ids up to <eos>, joined by spaces; <pad>/<sos> skipped, <unk> kept as "<unk>".
  std::string decode(const std::vector<int>& ids) const;

  int id(const std::string& word) const;  // kUnk when absent
  const std::string& word(int id) const;  // "<unk>" when out of range
  const std::vector<std::string>& words() const { return words_; }
  int size() const { return static_cast<int>(words_.size()); }

 private:
  std::vector<std::string> words_;
  std::unordered_map<std::string, int> index_;
};

}  // namespace mc
