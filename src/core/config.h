// Declarative configs: each section declares its fields once in visit(); that
// one declaration drives YAML parsing, validation, dumping and --describe.
//
//   struct OptimConfig : mc::Config {
//     double lr = 2e-4;
//     int warmup = 2000;
//     void visit(mc::FieldVisitor& v) override {
//       v("lr", lr, "peak learning rate", mc::positive<double>());
//       v("warmup", warmup, "linear warm-up steps", mc::at_least(0));
//     }
//   };
//
// Polymorphic parts (models, samplers, ...) are `Component`s: a `type:` key
// picks a registered config struct (see register_component below).
#pragma once
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <set>
#include <string>
#include <type_traits>
#include <vector>

#include <fmt/format.h>

namespace YAML {
class Node;
}

namespace mc {

// A validation rule: returns an empty string when the value is fine, else what
// is wrong; `text` documents the rule in --describe.
template <class T>
struct Check {
  std::function<std::string(const T&)> fn;
  std::string text;
};

template <class T>
Check<T> in_range(T lo, T hi) {
  return {[=](const T& v) { return (v >= lo && v <= hi) ? "" : fmt::format("must be in [{}, {}]", lo, hi); },
          fmt::format("in [{}, {}]", lo, hi)};
}
template <class T>
Check<T> at_least(T lo) {
  return {[=](const T& v) { return v >= lo ? "" : fmt::format("must be >= {}", lo); }, fmt::format(">= {}", lo)};
}
template <class T>
Check<T> positive() {
  return {[](const T& v) { return v > T(0) ? "" : std::string("must be > 0"); }, "> 0"};
}
Check<std::string> one_of(std::vector<std::string> allowed);
// Every element of a list satisfies `c`.
template <class T>
Check<std::vector<T>> each(Check<T> c) {
  return {[=](const std::vector<T>& v) {
            for (size_t i = 0; i < v.size(); ++i) {
              std::string e = c.fn(v[i]);
              if (!e.empty()) return fmt::format("element {} ({}) {}", i, v[i], e);
            }
            return std::string();
          },
          "each " + c.text};
}
template <class T>
Check<std::vector<T>> non_empty() {
  return {[](const std::vector<T>& v) { return v.empty() ? std::string("must not be empty") : std::string(); },
          "non-empty"};
}

class FieldVisitor;

// A config section. Subclasses declare fields in visit() and may add
// cross-field checks in validate() (return an error message or "").
struct Config {
  virtual ~Config() = default;
  virtual void visit(FieldVisitor& v) = 0;
  virtual std::string validate() const { return ""; }
  // True when this section, used as a field of another, is in its "off" state and
  // should be left out of dumps (and so of config hashes): an optional section
  // added later keeps the names of every run trained before it existed. Reading
  // an absent section gives its defaults, so the dump still parses back the same.
  virtual bool omitted_from_dump() const { return false; }
};

// A polymorphic section: `type` names a registered config struct.
struct Component {
  std::string family;  // e.g. "model"; fixed by the owning section
  std::string type;    // e.g. "motion_autoencoder"
  std::shared_ptr<Config> cfg;

  explicit Component(std::string fam, std::string default_type = "");
  template <class T>
  T& as() const {
    auto* p = dynamic_cast<T*>(cfg.get());
    if (!p) throw std::logic_error(fmt::format("component {} has type '{}', not the requested one", family, type));
    return *p;
  }
};

// Config-struct registry for Components: family -> type -> factory.
using ConfigFactory = std::function<std::shared_ptr<Config>()>;
void register_component(const std::string& family, const std::string& type, ConfigFactory make,
                        const std::string& help);
std::vector<std::string> component_types(const std::string& family);
std::shared_ptr<Config> make_component_config(const std::string& family, const std::string& type);
std::string component_help(const std::string& family, const std::string& type);

template <class T>
struct ComponentRegistration {
  ComponentRegistration(const char* family, const char* type, const char* help) {
    register_component(family, type, [] { return std::make_shared<T>(); }, help);
  }
};

// One overload per supported field type. Every concrete visitor (reader,
// writer, describer, comparer) implements them all.
class FieldVisitor {
 public:
  virtual ~FieldVisitor() = default;
#define MC_FIELD_TYPES(X)          \
  X(bool)                          \
  X(int)                           \
  X(int64_t)                       \
  X(double)                        \
  X(std::string)                   \
  X(std::vector<int>)              \
  X(std::vector<double>)           \
  X(std::vector<std::string>)
#define MC_DECLARE(T) virtual void field(const char* name, T& v, const char* help, const Check<T>& c) = 0;
  MC_FIELD_TYPES(MC_DECLARE)
#undef MC_DECLARE
  virtual void section(const char* name, Config& c, const char* help) = 0;
  virtual void component(const char* name, Component& c, const char* help) = 0;

  template <class T>
  void operator()(const char* name, T& v, const char* help) {
    if constexpr (std::is_base_of_v<Config, T>) section(name, v, help);
    else if constexpr (std::is_same_v<T, Component>) component(name, v, help);
    else field(name, v, help, Check<T>{});
  }
  template <class T>
  void operator()(const char* name, T& v, const char* help, const Check<T>& c) {
    field(name, v, help, c);
  }
};

// A composed YAML tree plus, for every leaf path, the file or override that set it.
struct ConfigSource {
  std::shared_ptr<YAML::Node> root;
  std::map<std::string, std::string> origin;  // "model.depth" -> "configs/model/flow_tiny.yaml"
  std::string main_file;
  std::vector<std::string> overrides;
  std::string origin_of(const std::string& path) const;
};

// Loads `file`, resolves its `defaults:` list recursively (group entries
// `- model: flow_tiny` -> <config root>/model/flow_tiny.yaml placed under
// `model`; plain entries `- base` -> file relative to this one, at the root;
// `_self_` marks where this file's own keys go, last by default), then applies
// `key=value` overrides (`group=name` swaps a defaults entry).
ConfigSource compose_config(const std::string& file, const std::vector<std::string>& overrides = {});
ConfigSource config_from_string(const std::string& yaml, const std::string& name = "<string>",
                                const std::vector<std::string>& overrides = {});

// Parses `src` into `cfg`: types, ranges, unknown keys ("did you mean"), all as
// UserError naming the file and key.
void parse_config(const ConfigSource& src, Config& cfg);

// Composes FILE + overrides and parses it as a T.
template <class T>
T load_job(const std::string& file, const std::vector<std::string>& overrides) {
  T cfg;
  parse_config(compose_config(file, overrides), cfg);
  return cfg;
}

// Composes `file`, applies each `substitutions` entry (path=value) whose path exists
// in the composed file (profile-wide knobs such as generator.sampler.steps that only
// some files have), then `overrides` (which must fit), and parses the one component
// under `key` (e.g. "generator") into `out`. Returns the resolved `key:` section as YAML.
std::string parse_component_file(const std::string& file, const std::string& key,
                                 const std::vector<std::string>& substitutions,
                                 const std::vector<std::string>& overrides, Component& out);

// Resolved config as YAML (every field, defaults included); parses back to the same config.
std::string dump_config(Config& cfg);
// Human-readable reference of every field (name, type, default, rule, help).
std::string describe_config(Config& cfg, const std::string& only_section = "");
// Equality through the field declarations.
bool configs_equal(Config& a, Config& b);
// Short stable hash of the dumped config (for caching trained components).
std::string config_hash(Config& cfg);

// Suggests the closest candidate to `word` ("" when nothing is close).
std::string did_you_mean(const std::string& word, const std::vector<std::string>& candidates);

}  // namespace mc
