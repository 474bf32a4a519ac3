// Config system: composition (defaults lists, groups, overrides), typed parsing,
// validation, unknown keys with "did you mean", dump round trip, describe.
#include <catch2/catch.hpp>

#include <filesystem>
#include <fstream>

#include "core/config.h"
#include "core/error.h"

namespace fs = std::filesystem;
using namespace mc;

namespace {

struct InnerCfg : Config {
  int depth = 4;
  double dropout = 0.1;
  std::vector<int> joints = {0, 10};
  void visit(FieldVisitor& v) override {
    v("depth", depth, "layers", at_least(1));
    v("dropout", dropout, "dropout", in_range(0.0, 1.0));
    v("joints", joints, "controlled joints", each(in_range(0, 21)));
  }
};

struct TinyModelCfg : Config {
  int width = 32;
  std::string act = "relu";
  void visit(FieldVisitor& v) override {
    v("width", width, "channels", positive<int>());
    v("act", act, "activation", one_of({"relu", "gelu"}));
  }
};
struct OtherModelCfg : Config {
  double scale = 1.5;
  void visit(FieldVisitor& v) override { v("scale", scale, "scale", positive<double>()); }
};
const ComponentRegistration<TinyModelCfg> reg_tiny("testmodel", "tiny", "a tiny test model");
const ComponentRegistration<OtherModelCfg> reg_other("testmodel", "other", "another test model");

struct RootCfg : Config {
  std::string name = "x";
  bool flag = false;
  int64_t seed = 7;
  std::vector<std::string> tags;
  InnerCfg inner;
  Component model{"testmodel", "tiny"};
  void visit(FieldVisitor& v) override {
    v("name", name, "name");
    v("flag", flag, "flag");
    v("seed", seed, "seed");
    v("tags", tags, "tags");
    v("inner", inner, "inner section");
    v("model", model, "model");
  }
};

struct TempDir {
  fs::path path;
  TempDir() {
    path = fs::temp_directory_path() / fmt::format("mc_cfg_{}_{}", ::getpid(), rand());
    fs::create_directories(path / "configs" / "model");
  }
  ~TempDir() { fs::remove_all(path); }
  fs::path write(const std::string& rel, const std::string& text) const {
    fs::path p = path / rel;
    fs::create_directories(p.parent_path());
    std::ofstream(p) << text;
    return p;
  }
};

std::string error_of(const std::function<void()>& f) {
  try {
    f();
  } catch (const UserError& e) {
    return e.what();
  }
  return "";
}

}  // namespace

TEST_CASE("defaults lists compose in order, later keys win, group files land under their key", "[config]") {
  TempDir t;
  t.write("configs/model/small.yaml", "type: tiny\nwidth: 64\n");
  t.write("configs/model/big.yaml", "type: tiny\nwidth: 512\nact: gelu\n");
  t.write("configs/base.yaml", "name: base\ninner: {depth: 2, dropout: 0.3}\n");
  auto main = t.write("configs/exp.yaml",
                      "defaults:\n  - base\n  - model: small\n  - _self_\nname: exp\ninner: {depth: 6}\n");
  RootCfg c;
  parse_config(compose_config(main.string()), c);
  CHECK(c.name == "exp");          // own keys after defaults win
  CHECK(c.inner.depth == 6);       // deep merge keeps base's dropout
  CHECK(c.inner.dropout == Approx(0.3));
  CHECK(c.model.type == "tiny");
  CHECK(c.model.as<TinyModelCfg>().width == 64);

  SECTION("a group override swaps the file; value overrides are typed") {
    RootCfg d;
    parse_config(compose_config(main.string(), {"model=big", "inner.depth=9", "tags=[a, b]", "seed=12"}), d);
    CHECK(d.model.as<TinyModelCfg>().width == 512);
    CHECK(d.model.as<TinyModelCfg>().act == "gelu");
    CHECK(d.inner.depth == 9);
    CHECK(d.tags == std::vector<std::string>{"a", "b"});
    CHECK(d.seed == 12);
  }
  SECTION("_self_ first lets the defaults win") {
    auto f = t.write("configs/selffirst.yaml", "defaults: [_self_, base]\nname: mine\n");
    RootCfg d;
    parse_config(compose_config(f.string()), d);
    CHECK(d.name == "base");
  }
}

TEST_CASE("dumped config parses back to the same config", "[config]") {
  TempDir t;
  auto f = t.write("configs/a.yaml",
                   "name: \"quoted: yes\"\nflag: true\nseed: 123456789012\ntags: [x, 'y z', '12']\n"
                   "inner: {depth: 3, dropout: 0.25, joints: [0, 21]}\nmodel: {type: other, scale: 0.002}\n");
  RootCfg c;
  parse_config(compose_config(f.string()), c);
  std::string dump1 = dump_config(c);
  auto g = t.write("configs/b.yaml", dump1);
  RootCfg d;
  parse_config(compose_config(g.string()), d);
  CHECK(dump_config(d) == dump1);
  CHECK(configs_equal(c, d));
  CHECK(d.model.type == "other");
  CHECK(d.model.as<OtherModelCfg>().scale == Approx(0.002));
  CHECK(d.tags[2] == "12");
  CHECK(config_hash(c) == config_hash(d));
  RootCfg e;
  CHECK_FALSE(configs_equal(c, e));
}

TEST_CASE("bad configs give errors naming the file and key", "[config]") {
  TempDir t;
  SECTION("unknown key with did-you-mean") {
    auto f = t.write("configs/u.yaml", "inner: {detph: 3}\n");
    RootCfg c;
    std::string e = error_of([&] { parse_config(compose_config(f.string()), c); });
    CHECK(e.find("u.yaml") != std::string::npos);
    CHECK(e.find("inner.detph") != std::string::npos);
    CHECK(e.find("did you mean 'depth'") != std::string::npos);
  }
  SECTION("wrong type") {
    auto f = t.write("configs/w.yaml", "inner: {depth: three}\n");
    RootCfg c;
    std::string e = error_of([&] { parse_config(compose_config(f.string()), c); });
    CHECK(e.find("w.yaml") != std::string::npos);
    CHECK(e.find("inner.depth") != std::string::npos);
    CHECK(e.find("must be a int") != std::string::npos);
  }
  SECTION("out of range, from an override") {
    auto f = t.write("configs/r.yaml", "name: r\n");
    RootCfg c;
    std::string e = error_of([&] { parse_config(compose_config(f.string(), {"inner.dropout=1.5"}), c); });
    CHECK(e.find("override 'inner.dropout=1.5'") != std::string::npos);
    CHECK(e.find("[0, 1]") != std::string::npos);
    RootCfg fresh;  // a failed parse leaves `c` half-updated
    e = error_of([&] { parse_config(compose_config(f.string(), {"inner.joints=[0, 22]"}), fresh); });
    CHECK(e.find("element 1") != std::string::npos);
  }
  SECTION("malformed YAML names file and line") {
    auto f = t.write("configs/m.yaml", "name: x\ninner: {depth: 3\n");
    std::string e = error_of([&] { compose_config(f.string()); });
    CHECK(e.find("m.yaml:") != std::string::npos);
    CHECK(e.find("malformed YAML") != std::string::npos);
  }
  SECTION("unknown component type and missing group file") {
    auto f = t.write("configs/c.yaml", "model: {type: tiyn}\n");
    RootCfg c;
    std::string e = error_of([&] { parse_config(compose_config(f.string()), c); });
    CHECK(e.find("did you mean 'tiny'") != std::string::npos);
    auto g = t.write("configs/g.yaml", "defaults: [{model: nosuch}]\n");
    e = error_of([&] { compose_config(g.string()); });
    CHECK(e.find("nosuch") != std::string::npos);
  }
  SECTION("non-finite floats and malformed overrides are refused") {
    auto f = t.write("configs/n.yaml", "inner: {dropout: .nan}\n");
    RootCfg c;
    CHECK_FALSE(error_of([&] { parse_config(compose_config(f.string()), c); }).empty());
    CHECK(error_of([&] { compose_config(f.string(), {"noequals"}); }).find("key.path=value") != std::string::npos);
    CHECK(error_of([&] { compose_config(f.string(), {"inner.dropout.x=1"}); }).find("is a value") !=
          std::string::npos);
  }
  SECTION("missing file") {
    CHECK(error_of([&] { compose_config((t.path / "none.yaml").string()); }).find("does not exist") !=
          std::string::npos);
  }
}

TEST_CASE("describe lists every field with type, default and rule", "[config]") {
  RootCfg c;
  std::string d = describe_config(c);
  CHECK(d.find("inner.depth") != std::string::npos);
  CHECK(d.find(">= 1") != std::string::npos);
  CHECK(d.find("model.type") != std::string::npos);
  CHECK(d.find("with type: other") != std::string::npos);
  CHECK(describe_config(c, "inner").find("inner.dropout") != std::string::npos);
  CHECK_THROWS_AS(describe_config(c, "inenr"), UserError);
}

TEST_CASE("did_you_mean picks the closest candidate or nothing", "[config]") {
  CHECK(did_you_mean("lr", {"lr_min", "lr", "steps"}) == "lr");
  CHECK(did_you_mean("stpes", {"lr", "steps"}) == "steps");
  CHECK(did_you_mean("zzzzzz", {"lr", "steps"}).empty());
}
