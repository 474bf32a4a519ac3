// Caption tokenizer and vocabulary: splitting rules, frequency ordering,
// min_count, encode/decode round trips and storage in a motion file.
#include <catch2/catch.hpp>

#include "core/error.h"
#include "data/text_vocab.h"
#include "data_test_util.h"

using namespace mc;

TEST_CASE("tokenize: lowercase, split on non-letters, apostrophes split", "[data]") {
  CHECK(tokenize_caption("A person WALKS forward.") == std::vector<std::string>{"a", "person", "walks", "forward"});
  CHECK(tokenize_caption("  don't stop--then jump 3 times!") ==
        std::vector<std::string>{"don", "t", "stop", "then", "jump", "times"});
  CHECK(tokenize_caption("café ça") == std::vector<std::string>{"café", "ça"});
  CHECK(tokenize_caption("...123...").empty());
}

TEST_CASE("vocabulary: specials first, then by frequency, ties alphabetical, min_count", "[data]") {
  const std::vector<std::string> caps = {"a person walks", "A person runs", "the person walks fast", "zebra"};
  TextVocab v = TextVocab::build(caps);
  // person x3; a x2, walks x2; fast, runs, the, zebra x1.
  CHECK(v.words() == std::vector<std::string>{"<pad>", "<unk>", "<sos>", "<eos>", "person", "a", "walks", "fast",
                                              "runs", "the", "zebra"});
  CHECK(v.id("<pad>") == TextVocab::kPad);
  CHECK(v.id("<unk>") == TextVocab::kUnk);
  CHECK(v.id("person") == 4);

  TextVocab common = TextVocab::build(caps, 2);
  CHECK(common.words() == std::vector<std::string>{"<pad>", "<unk>", "<sos>", "<eos>", "person", "a", "walks"});
  CHECK(common.id("zebra") == TextVocab::kUnk);
  CHECK_THROWS_AS(TextVocab::build(caps, 0), UserError);
}

TEST_CASE("encode/decode round trip, unknown words become <unk>, truncation keeps <eos>", "[data]") {
  TextVocab v = TextVocab::build({"a person walks forward", "a person turns left", "someone jumps"});
  auto e = v.encode("A person walks forward", 10);
  REQUIRE(e.ids.size() == 10);
  CHECK(e.length == 6);
  CHECK(e.ids[0] == TextVocab::kSos);
  CHECK(e.ids[5] == TextVocab::kEos);
  CHECK(e.ids[6] == TextVocab::kPad);
  CHECK(e.ids[9] == TextVocab::kPad);
  CHECK(v.decode(e.ids) == "a person walks forward");

  auto u = v.encode("a person dances wildly", 8);
  CHECK(u.ids[3] == TextVocab::kUnk);
  CHECK(u.ids[4] == TextVocab::kUnk);
  CHECK(v.decode(u.ids) == "a person <unk> <unk>");

  auto t = v.encode("a person walks forward then turns left", 5);
  CHECK(t.length == 5);
  CHECK(t.ids == std::vector<int>{TextVocab::kSos, v.id("a"), v.id("person"), v.id("walks"), TextVocab::kEos});
  CHECK(v.decode(t.ids) == "a person walks");

  auto empty = v.encode("!!!", 4);
  CHECK(empty.length == 2);
  CHECK(v.decode(empty.ids).empty());
  CHECK_THROWS_AS(v.encode("x", 1), UserError);

  // Every in-vocabulary caption survives the round trip (normalised by the tokenizer).
  for (const std::string c : {"Someone jumps.", "A PERSON turns left", "left left left"})
    CHECK(v.decode(v.encode(c, 16).ids) == [&] {
      std::string s;
      for (auto& w : tokenize_caption(c)) s += (s.empty() ? "" : " ") + w;
      return s;
    }());
}

TEST_CASE("vocabulary from a motion set's train captions, stored and restored", "[data][io]") {
  MotionSet m = test::random_motion_set({3, 3, 3}, {"train", "test", "train"});
  m.captions[0] = {"a person walks", "walks walks"};
  m.captions[1] = {"secret test words"};
  m.captions[2] = {"a person sits"};
  TextVocab v = TextVocab::build(m);
  CHECK(v.id("secret") == TextVocab::kUnk);  // test captions do not leak in
  CHECK(v.words()[4] == "walks");
  m.vocab = v.words();

  test::ScratchDir dir;
  write_motion_file(dir.file("v.h5"), m);
  TextVocab back(read_motion_file(dir.file("v.h5")).vocab);
  CHECK(back.words() == v.words());
  CHECK(back.encode("a person walks", 6).ids == v.encode("a person walks", 6).ids);

  CHECK_THROWS_AS(TextVocab(std::vector<std::string>{"walks", "<pad>"}), UserError);
  CHECK_THROWS_AS(TextVocab(std::vector<std::string>{"<pad>", "<unk>", "<sos>", "<eos>", "a", "a"}), UserError);
}
