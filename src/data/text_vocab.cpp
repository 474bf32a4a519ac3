// Caption tokenization and the frequency-ordered word vocabulary.
#include "data/text_vocab.h"

#include <algorithm>
#include <map>

#include "core/error.h"

namespace mc {

std::vector<std::string> tokenize_caption(const std::string& caption) {
  std::vector<std::string> words;
  std::string current;
  for (char ch : caption) {
    const auto c = static_cast<unsigned char>(ch);
    if (c >= 'A' && c <= 'Z') {
      current += static_cast<char>(c - 'A' + 'a');
    } else if ((c >= 'a' && c <= 'z') || c >= 0x80) {
      current += ch;
    } else if (!current.empty()) {
      words.push_back(std::move(current));
      current.clear();
    }
  }
  if (!current.empty()) words.push_back(std::move(current));
  return words;
}

const std::vector<std::string>& TextVocab::special_tokens() {
  static const std::vector<std::string> specials = {"<pad>", "<unk>", "<sos>", "<eos>"};
  return specials;
}

TextVocab TextVocab::build(const std::vector<std::string>& captions, int min_count) {
  if (min_count < 1) fail("vocabulary min_count must be >= 1 (got {})", min_count);
  std::map<std::string, int> counts;
  for (auto& c : captions)
    for (auto& w : tokenize_caption(c)) ++counts[w];
  std::vector<std::pair<std::string, int>> kept;
  for (auto& [w, n] : counts)
    if (n >= min_count) kept.emplace_back(w, n);
  // counts is ordered by word, so a stable sort by count keeps ties alphabetical.
  std::stable_sort(kept.begin(), kept.end(), [](auto& a, auto& b) { return a.second > b.second; });
  std::vector<std::string> words = special_tokens();
  for (auto& [w, n] : kept) words.push_back(w);
  return TextVocab(std::move(words));
}

TextVocab TextVocab::build(const MotionSet& m, const std::string& split, int min_count) {
  std::vector<std::string> captions;
  for (size_t i : m.indices_of_split(split)) captions.insert(captions.end(), m.captions[i].begin(), m.captions[i].end());
  if (captions.empty()) fail("cannot build a vocabulary: the motion set has no captions in split '{}'", split);
  return build(captions, min_count);
}

TextVocab::TextVocab(std::vector<std::string> words, const std::string& source) : words_(std::move(words)) {
  const auto& specials = special_tokens();
  if (words_.size() < specials.size() || !std::equal(specials.begin(), specials.end(), words_.begin()))
    fail("{}: a vocabulary must start with <pad>, <unk>, <sos>, <eos> (ids 0-3); rebuild it from the captions",
         source);
  for (size_t i = 0; i < words_.size(); ++i)
    if (!index_.emplace(words_[i], static_cast<int>(i)).second)
      fail("{}: the vocabulary lists '{}' twice; rebuild it from the captions", source, words_[i]);
}

TextVocab::Encoded TextVocab::encode(const std::string& caption, int max_len) const {
  if (max_len < 2) fail("text max_len must be >= 2 to hold <sos> and <eos> (got {})", max_len);
  auto words = tokenize_caption(caption);
  if (words.size() > static_cast<size_t>(max_len - 2)) words.resize(max_len - 2);
  Encoded e;
  e.ids.reserve(max_len);
  e.ids.push_back(kSos);
  for (auto& w : words) e.ids.push_back(id(w));
  e.ids.push_back(kEos);
  e.length = static_cast<int>(e.ids.size());
  e.ids.resize(max_len, kPad);
  return e;
}

std::string TextVocab::decode(const std::vector<int>& ids) const {
  std::string out;
  for (int i : ids) {
    if (i == kEos) break;
    if (i == kPad || i == kSos) continue;
    if (!out.empty()) out += ' ';
    out += word(i);
  }
  return out;
}

int TextVocab::id(const std::string& w) const {
  auto it = index_.find(w);
  return it == index_.end() ? kUnk : it->second;
}

const std::string& TextVocab::word(int i) const {
  return i >= 0 && i < size() ? words_[i] : words_[kUnk];
}

}  // namespace mc
