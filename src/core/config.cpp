// YAML composition (defaults lists, overrides, origin tracking) and the visitors
// that parse, dump, describe and compare declared config sections.
#include "core/config.h"

#include <yaml-cpp/yaml.h>

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "core/error.h"
#include "core/yaml_strict.h"

namespace mc {
namespace fs = std::filesystem;

// ---------------------------------------------------------------- strict YAML

namespace {

struct StrictWalk {
  const std::string& name;
  const std::string& what;
  size_t visited = 0;

  static int line_of(const YAML::Node& n) { return n.Mark().line + 1; }

  void walk(const YAML::Node& n, int depth) {
    if (++visited > 1000000)
      fail("{}: {} too large: more than a million values (aliases expanding?); simplify the file", name, what);
    if (depth > 64)
      fail("{}:{}: {} nested deeper than 64 levels (a recursive alias?); simplify the file", name, line_of(n), what);
    if (n.IsSequence()) {
      for (auto e : n) walk(e, depth + 1);
    } else if (n.IsMap()) {
      std::map<std::string, int> seen;
      for (auto kv : n) {
        if (!kv.first.IsScalar())
          fail("{}:{}: {}: a key is a {} (a complex key); keys must be plain names", name, line_of(kv.first), what,
               kv.first.IsSequence() ? "list" : kv.first.IsMap() ? "mapping" : "null");
        const std::string key = kv.first.Scalar();
        auto [it, fresh] = seen.emplace(key, line_of(kv.first));
        if (!fresh)
          fail("{}:{}: {}: key '{}' is given twice (first on line {}); remove one of them", name, line_of(kv.first),
               what, key, it->second);
        walk(kv.second, depth + 1);
      }
    }
  }
};

// Line (1-based) where the second document starts: the second '---' line, or the
// first one after a '...' end marker or after content.
int second_document_line(const std::string& text) {
  std::istringstream in(text);
  std::string line;
  int no = 0;
  bool content = false;
  while (std::getline(in, line)) {
    ++no;
    const bool marker = line.rfind("---", 0) == 0 && (line.size() == 3 || std::isspace(static_cast<unsigned char>(line[3])));
    if (marker && content) return no;
    if (line.rfind("...", 0) == 0) {
      content = true;
      continue;
    }
    if (marker) {
      content = true;  // the first '---' opens document one
      continue;
    }
    auto first = line.find_first_not_of(" \t\r");
    if (first != std::string::npos && line[first] != '#' && line[first] != '%') content = true;
  }
  return 0;
}

}  // namespace

YAML::Node parse_yaml_strict(const std::string& text, const std::string& name, const std::string& what) {
  std::vector<YAML::Node> docs;
  try {
    docs = YAML::LoadAll(text);
  } catch (const YAML::Exception& e) {
    fail("{}:{}:{}: malformed {}: {}", name, e.mark.line + 1, e.mark.column + 1, what, e.msg);
  }
  if (docs.size() > 1) {
    int line = docs[1].Mark().line >= 0 ? docs[1].Mark().line + 1 : second_document_line(text);
    fail("{}:{}: {} holds a second document (after '---'); a file holds one document: remove the separator or "
         "split the file",
         name, line, what);
  }
  if (docs.empty()) return YAML::Node();
  StrictWalk{name, what}.walk(docs[0], 0);
  return docs[0];
}

YAML::Node load_yaml_file_strict(const std::string& path, const std::string& what) {
  std::error_code ec;
  if (!fs::exists(path, ec)) fail("{} file '{}' does not exist", what, path);
  if (fs::is_directory(path, ec)) fail("'{}' is a directory, not a {} file; give the path of a .yaml file", path, what);
  std::ifstream in(path, std::ios::binary);
  if (!in) fail("{} file '{}' cannot be read (permission denied?)", what, path);
  std::stringstream ss;
  ss << in.rdbuf();
  return parse_yaml_strict(ss.str(), path, what);
}

// ---------------------------------------------------------------- helpers

Check<std::string> one_of(std::vector<std::string> allowed) {
  std::string joined;
  for (auto& a : allowed) joined += (joined.empty() ? "" : "|") + a;
  return {[=](const std::string& v) {
            if (std::find(allowed.begin(), allowed.end(), v) != allowed.end()) return std::string();
            std::string hint = did_you_mean(v, allowed);
            return fmt::format("must be one of {}{}", joined, hint.empty() ? "" : " (did you mean '" + hint + "'?)");
          },
          "one of " + joined};
}

static size_t edit_distance(const std::string& a, const std::string& b) {
  std::vector<size_t> prev(b.size() + 1), cur(b.size() + 1);
  for (size_t j = 0; j <= b.size(); ++j) prev[j] = j;
  for (size_t i = 1; i <= a.size(); ++i) {
    cur[0] = i;
    for (size_t j = 1; j <= b.size(); ++j)
      cur[j] = std::min({prev[j] + 1, cur[j - 1] + 1, prev[j - 1] + (a[i - 1] == b[j - 1] ? 0 : 1)});
    std::swap(prev, cur);
  }
  return prev[b.size()];
}

std::string did_you_mean(const std::string& word, const std::vector<std::string>& candidates) {
  std::string best;
  size_t best_d = std::max<size_t>(2, word.size() / 3) + 1;
  for (auto& c : candidates) {
    size_t d = edit_distance(word, c);
    if (d < best_d) best_d = d, best = c;
  }
  return best;
}

static std::string hint_suffix(const std::string& word, const std::vector<std::string>& candidates) {
  std::string h = did_you_mean(word, candidates);
  return h.empty() ? "" : fmt::format(" (did you mean '{}'?)", h);
}

// ---------------------------------------------------------------- registry

namespace {
struct RegEntry {
  ConfigFactory make;
  std::string help;
};
std::map<std::string, std::map<std::string, RegEntry>>& registry() {
  static std::map<std::string, std::map<std::string, RegEntry>> r;
  return r;
}
}  // namespace

void register_component(const std::string& family, const std::string& type, ConfigFactory make,
                        const std::string& help) {
  registry()[family][type] = RegEntry{std::move(make), help};
}

std::vector<std::string> component_types(const std::string& family) {
  std::vector<std::string> out;
  auto it = registry().find(family);
  if (it != registry().end())
    for (auto& [k, _] : it->second) out.push_back(k);
  return out;
}

std::shared_ptr<Config> make_component_config(const std::string& family, const std::string& type) {
  auto types = component_types(family);
  auto& fam = registry()[family];
  auto it = fam.find(type);
  if (it == fam.end()) {
    std::string all;
    for (auto& t : types) all += (all.empty() ? "" : ", ") + t;
    fail("unknown {} type '{}'{}; registered types: {}", family, type, hint_suffix(type, types),
         all.empty() ? "(none)" : all);
  }
  return it->second.make();
}

std::string component_help(const std::string& family, const std::string& type) {
  auto& fam = registry()[family];
  auto it = fam.find(type);
  return it == fam.end() ? "" : it->second.help;
}

Component::Component(std::string fam, std::string default_type) : family(std::move(fam)), type(std::move(default_type)) {
  if (!type.empty()) cfg = make_component_config(family, type);
}

// ---------------------------------------------------------------- composition

std::string ConfigSource::origin_of(const std::string& path) const {
  // The most specific recorded origin: the path itself or its nearest ancestor.
  std::string p = path;
  while (true) {
    auto it = origin.find(p);
    if (it != origin.end()) return it->second;
    auto dot = p.rfind('.');
    if (dot == std::string::npos) break;
    p = p.substr(0, dot);
  }
  // Or, for a section, any descendant (all descendants share a file in practice).
  auto it = origin.lower_bound(path + ".");
  if (it != origin.end() && it->first.rfind(path + ".", 0) == 0) return it->second;
  return main_file;
}

namespace {

struct Loaded {
  YAML::Node node;
  std::map<std::string, std::string> origin;
};

std::string join_path(const std::string& prefix, const std::string& key) {
  return prefix.empty() ? key : prefix + "." + key;
}

void record_leaves(const YAML::Node& n, const std::string& path, const std::string& file,
                   std::map<std::string, std::string>& origin) {
  if (n.IsMap() && n.size() > 0) {
    for (auto kv : n) record_leaves(kv.second, join_path(path, kv.first.as<std::string>()), file, origin);
  } else {
    origin[path] = file;
  }
}

void erase_below(std::map<std::string, std::string>& origin, const std::string& path) {
  auto it = origin.lower_bound(path + ".");
  while (it != origin.end() && it->first.rfind(path + ".", 0) == 0) it = origin.erase(it);
}

// Deep-merges `src` into `dst` (maps merge, everything else replaces).
void merge_into(YAML::Node dst, const YAML::Node& src, const std::string& path,
                const std::map<std::string, std::string>& src_origin, const std::string& src_prefix,
                std::map<std::string, std::string>& origin) {
  for (auto kv : src) {
    std::string key = kv.first.as<std::string>();
    std::string p = join_path(path, key);
    std::string sp = join_path(src_prefix, key);
    YAML::Node d = dst[key];
    if (d.IsMap() && kv.second.IsMap()) {
      merge_into(d, kv.second, p, src_origin, sp, origin);
    } else {
      dst[key] = YAML::Clone(kv.second);
      erase_below(origin, p);
      origin.erase(p);
      // carry over the source's origins for this subtree
      auto it = src_origin.lower_bound(sp);
      for (; it != src_origin.end() && (it->first == sp || it->first.rfind(sp + ".", 0) == 0); ++it)
        origin[p + it->first.substr(sp.size())] = it->second;
    }
  }
}

YAML::Node load_yaml_file(const fs::path& file) {
  std::error_code ec;
  if (!fs::exists(file, ec)) fail("config file '{}' does not exist", file.string());
  if (fs::is_directory(file, ec))
    fail("config '{}' is a directory; give the path of a .yaml file (e.g. {}/<name>.yaml)", file.string(),
         file.string());
  return load_yaml_file_strict(file.string(), "YAML");
}

fs::path find_config_root(const fs::path& file) {
  if (const char* env = std::getenv("MOTIONCTL_CONFIG_ROOT")) return env;
  for (fs::path p = fs::absolute(file).parent_path(); !p.empty(); p = p.parent_path()) {
    if (p.filename() == "configs") return p;
    if (p == p.root_path()) break;
  }
  return fs::absolute(file).parent_path();
}

fs::path with_yaml_ext(fs::path p) {
  if (p.extension() != ".yaml" && p.extension() != ".yml") p += ".yaml";
  return p;
}

struct Composer {
  fs::path root;
  std::map<std::string, std::string> group_swaps;  // from `group=name` overrides
  std::set<std::string> groups_seen;
  std::vector<std::string> stack;

  Loaded load(const YAML::Node& raw, const std::string& name, const fs::path& dir) {
    Loaded out;
    out.node = YAML::Node(YAML::NodeType::Map);
    if (raw.IsNull()) return out;
    if (!raw.IsMap()) fail("{}: the top level of a config must be a mapping of keys to values", name);
    YAML::Node own = YAML::Clone(raw);
    YAML::Node defaults;
    if (own["defaults"]) {
      defaults = raw["defaults"];  // not the clone: clones lose line marks
      own.remove("defaults");
      if (!defaults.IsSequence())
        fail("{}: 'defaults' must be a list like [model: flow_tiny, _self_]", name);
    }
    std::map<std::string, std::string> own_origin;
    record_leaves(own, "", name, own_origin);
    own_origin.erase("");
    bool self_done = false;
    auto merge_self = [&] {
      merge_into(out.node, own, "", own_origin, "", out.origin);
      self_done = true;
    };
    for (auto entry : defaults) {
      if (entry.IsScalar()) {
        std::string s = entry.as<std::string>();
        if (s == "_self_") {
          merge_self();
          continue;
        }
        fs::path f = with_yaml_ext(dir / s);
        Loaded sub = load_file(f);
        merge_into(out.node, sub.node, "", sub.origin, "", out.origin);
      } else if (entry.IsMap() && entry.size() == 1) {
        auto kv = *entry.begin();
        std::string group = kv.first.as<std::string>();
        groups_seen.insert(group);
        if (kv.second.IsNull()) continue;
        if (!kv.second.IsScalar())
          fail("{}:{}: defaults entry '{}' names a {} instead of one config name; write '{}: <name>'", name,
               kv.second.Mark().line + 1, group, kv.second.IsSequence() ? "list" : "mapping", group);
        std::string choice = kv.second.as<std::string>();
        if (auto it = group_swaps.find(group); it != group_swaps.end()) choice = it->second;
        fs::path f = with_yaml_ext(root / group / choice);
        if (!fs::exists(f)) {
          std::vector<std::string> options;
          if (fs::is_directory(root / group))
            for (auto& e : fs::directory_iterator(root / group))
              if (e.path().extension() == ".yaml") options.push_back(e.path().stem().string());
          std::sort(options.begin(), options.end());
          std::string all;
          for (auto& o : options) all += (all.empty() ? "" : ", ") + o;
          fail("{}: defaults entry '{}: {}' names '{}', which does not exist{}; available: {}", name, group, choice,
               f.string(), hint_suffix(choice, options), all.empty() ? "(none)" : all);
        }
        Loaded sub = load_file(f);
        // group "a/b" places the file under key path a.b
        std::string package = group;
        std::replace(package.begin(), package.end(), '/', '.');
        YAML::Node wrapped(YAML::NodeType::Map);
        std::map<std::string, std::string> wrapped_origin;
        {
          std::vector<std::string> parts;
          std::stringstream ss(package);
          for (std::string part; std::getline(ss, part, '.');) parts.push_back(part);
          YAML::Node inner = sub.node;
          for (auto it = parts.rbegin(); it != parts.rend(); ++it) {
            YAML::Node m(YAML::NodeType::Map);
            m[*it] = inner;
            inner.reset(m);
          }
          wrapped.reset(inner);
          for (auto& [k, v] : sub.origin) wrapped_origin[join_path(package, k)] = v;
          if (sub.origin.empty()) wrapped_origin[package] = f.string();
        }
        merge_into(out.node, wrapped, "", wrapped_origin, "", out.origin);
      } else {
        fail("{}:{}: defaults entries must be 'group: name', a file name, or _self_", name, entry.Mark().line + 1);
      }
    }
    if (!self_done) merge_self();
    return out;
  }

  Loaded load_file(const fs::path& f) {
    std::string key = fs::weakly_canonical(f).string();
    if (std::find(stack.begin(), stack.end(), key) != stack.end())
      fail("config '{}' includes itself through its defaults list", f.string());
    stack.push_back(key);
    Loaded l = load(load_yaml_file(f), f.string(), f.parent_path());
    stack.pop_back();
    return l;
  }
};

void apply_override(ConfigSource& src, const std::string& ov) {
  auto eq = ov.find('=');
  if (eq == std::string::npos || eq == 0)
    fail("override '{}' must look like key.path=value (e.g. train.lr=1e-4)", ov);
  std::string key = ov.substr(0, eq), text = ov.substr(eq + 1);
  YAML::Node value;
  try {
    value = text.empty() ? YAML::Node(std::string()) : parse_yaml_strict(text, fmt::format("override '{}'", ov), "value");
  } catch (const YAML::Exception& e) {
    fail("override '{}': value is not valid YAML: {}", ov, e.msg);
  }
  std::vector<std::string> parts;
  std::stringstream ss(key);
  for (std::string part; std::getline(ss, part, '.');) {
    if (part.empty()) fail("override '{}': empty key segment", ov);
    parts.push_back(part);
  }
  YAML::Node cur = *src.root;
  std::string path;
  for (size_t i = 0; i + 1 < parts.size(); ++i) {
    path = join_path(path, parts[i]);
    YAML::Node next = cur[parts[i]];
    if (!next || next.IsNull()) {
      cur[parts[i]] = YAML::Node(YAML::NodeType::Map);
      next = cur[parts[i]];
    } else if (!next.IsMap()) {
      fail("override '{}': '{}' is a value, not a section", ov, path);
    }
    cur.reset(next);
  }
  cur[parts.back()] = value;
  erase_below(src.origin, key);
  src.origin[key] = fmt::format("override '{}'", ov);
}

ConfigSource finish(Composer& c, const YAML::Node& raw, const std::string& name, const fs::path& dir,
                    const std::vector<std::string>& overrides) {
  // Group swaps (`model=flow_small`) must be known before the defaults load.
  std::vector<std::string> value_overrides;
  YAML::Node defaults = raw.IsMap() ? raw["defaults"] : YAML::Node();
  std::set<std::string> top_groups;
  if (defaults && defaults.IsSequence())
    for (auto e : defaults)
      if (e.IsMap() && e.size() == 1) top_groups.insert(e.begin()->first.as<std::string>());
  for (auto& ov : overrides) {
    auto eq = ov.find('=');
    std::string key = eq == std::string::npos ? ov : ov.substr(0, eq);
    if (eq != std::string::npos && top_groups.count(key)) {
      c.group_swaps[key] = ov.substr(eq + 1);
    } else {
      value_overrides.push_back(ov);
    }
  }
  ConfigSource src;
  src.main_file = name;
  src.overrides = overrides;
  Loaded l = c.load(raw, name, dir);
  src.root = std::make_shared<YAML::Node>(l.node);
  src.origin = std::move(l.origin);
  for (auto& ov : value_overrides) apply_override(src, ov);
  return src;
}

}  // namespace

ConfigSource compose_config(const std::string& file, const std::vector<std::string>& overrides) {
  Composer c;
  c.root = find_config_root(file);
  c.stack.push_back(fs::weakly_canonical(file).string());
  return finish(c, load_yaml_file(file), file, fs::path(file).parent_path(), overrides);
}

ConfigSource config_from_string(const std::string& yaml, const std::string& name,
                                const std::vector<std::string>& overrides) {
  Composer c;
  c.root = fs::current_path() / "configs";
  YAML::Node raw = parse_yaml_strict(yaml, name, "YAML");
  return finish(c, raw, name, fs::current_path(), overrides);
}

// ---------------------------------------------------------------- scalar text

namespace {

template <class T>
const char* type_name();
template <> const char* type_name<bool>() { return "bool"; }
template <> const char* type_name<int>() { return "int"; }
template <> const char* type_name<int64_t>() { return "int64"; }
template <> const char* type_name<double>() { return "float"; }
template <> const char* type_name<std::string>() { return "string"; }
template <> const char* type_name<std::vector<int>>() { return "list of int"; }
template <> const char* type_name<std::vector<double>>() { return "list of float"; }
template <> const char* type_name<std::vector<std::string>>() { return "list of string"; }

std::string to_text(bool v) { return v ? "true" : "false"; }
std::string to_text(int v) { return std::to_string(v); }
std::string to_text(int64_t v) { return std::to_string(v); }
std::string to_text(double v) {
  std::string s = fmt::format("{}", v);
  if (s.find_first_of(".eEn") == std::string::npos) s += ".0";  // keep floats visibly floats
  return s;
}
std::string to_text(const std::string& v) { return v; }
template <class T>
std::string to_text(const std::vector<T>& v) {
  std::string s = "[";
  for (size_t i = 0; i < v.size(); ++i) s += (i ? ", " : "") + to_text(v[i]);
  return s + "]";
}

// Converts a YAML scalar; returns false when the text is not a T.
template <class T>
bool scalar_as(const YAML::Node& n, T& out) {
  if (!n.IsScalar()) return false;
  try {
    out = n.as<T>();
  } catch (const YAML::Exception&) {
    return false;
  }
  if constexpr (std::is_same_v<T, double>) {
    if (!std::isfinite(out)) return false;  // NaN/inf are never valid settings
  }
  return true;
}

std::string node_text(const YAML::Node& n) {
  if (n.IsScalar()) return n.Scalar();
  YAML::Emitter e;
  e << YAML::Flow << n;
  return e.c_str();
}

// ---------------------------------------------------------------- reader

class Reader : public FieldVisitor {
 public:
  Reader(const ConfigSource& src, YAML::Node node, std::string path)
      : src_(src), node_(std::move(node)), path_(std::move(path)) {}

#define MC_READ(T) \
  void field(const char* name, T& v, const char* help, const Check<T>& c) override { read(name, v, c); }
  MC_FIELD_TYPES(MC_READ)
#undef MC_READ

  void section(const char* name, Config& cfg, const char*) override {
    known_.push_back(name);
    YAML::Node n = node_[name];
    std::string p = join_path(path_, name);
    if (n && !n.IsNull() && !n.IsMap())
      fail("{}: '{}' must be a section (a mapping of keys), got '{}'", src_.origin_of(p), p, node_text(n));
    read_section(src_, n && n.IsMap() ? n : YAML::Node(YAML::NodeType::Map), p, cfg);
  }

  void component(const char* name, Component& c, const char*) override {
    known_.push_back(name);
    YAML::Node n = node_[name];
    std::string p = join_path(path_, name);
    if (n && !n.IsNull() && !n.IsMap())
      fail("{}: '{}' must be a section with a 'type:' key, got '{}'", src_.origin_of(p), p, node_text(n));
    YAML::Node m = n && n.IsMap() ? n : YAML::Node(YAML::NodeType::Map);
    std::string type = c.type;
    if (m["type"]) {
      if (!scalar_as(m["type"], type)) fail("{}: '{}.type' must be a name", src_.origin_of(p + ".type"), p);
    }
    if (type.empty()) {
      std::string all;
      for (auto& t : component_types(c.family)) all += (all.empty() ? "" : ", ") + t;
      fail("{}: '{}' needs a 'type:' key; one of: {}", src_.origin_of(p), p, all);
    }
    if (!c.cfg || type != c.type) {
      try {
        c.cfg = make_component_config(c.family, type);
      } catch (const UserError& e) {
        fail("{}: '{}.type': {}", src_.origin_of(p + ".type"), p, e.what());
      }
      c.type = type;
    }
    read_section(src_, m, p, *c.cfg, {"type"});
  }

  static void read_section(const ConfigSource& src, const YAML::Node& node, const std::string& path, Config& cfg,
                           std::vector<std::string> extra_known = {}) {
    Reader r(src, node, path);
    r.known_ = std::move(extra_known);
    cfg.visit(r);
    for (auto kv : node) {
      std::string key = kv.first.as<std::string>();
      if (std::find(r.known_.begin(), r.known_.end(), key) == r.known_.end()) {
        std::string p = join_path(path, key);
        fail("{}: unknown key '{}'{}; valid keys here: {}", src.origin_of(p), p, hint_suffix(key, r.known_),
             fmt::format("{}", fmt::join(r.known_, ", ")));
      }
    }
    std::string err = cfg.validate();
    if (!err.empty()) fail("{}: section '{}': {}", src.origin_of(path), path.empty() ? "<root>" : path, err);
  }

 private:
  template <class T>
  void read(const char* name, T& v, const Check<T>& c) {
    known_.push_back(name);
    YAML::Node n = node_[name];
    std::string p = join_path(path_, name);
    if (n) {
      bool ok = true;
      if constexpr (std::is_same_v<T, std::string>) {
        if (n.IsNull()) v.clear();
        else ok = scalar_as(n, v);
      } else if constexpr (std::is_same_v<T, std::vector<int>> || std::is_same_v<T, std::vector<double>> ||
                           std::is_same_v<T, std::vector<std::string>>) {
        T out;
        if (n.IsSequence()) {
          for (auto e : n) {
            typename T::value_type x;
            if (!scalar_as(e, x)) ok = false;
            out.push_back(x);
          }
        } else if (n.IsScalar()) {  // `key=5` on the command line means [5]
          typename T::value_type x;
          ok = scalar_as(n, x);
          out.push_back(x);
        } else if (n.IsNull()) {
          out.clear();
        } else {
          ok = false;
        }
        if (ok) v = out;
      } else {
        ok = scalar_as(n, v);
      }
      if (!ok)
        fail("{}: '{}' must be a {}, got '{}'", src_.origin_of(p), p, type_name<T>(), node_text(n));
    }
    if (c.fn) {
      std::string err = c.fn(v);
      if (!err.empty()) fail("{}: '{}' = {} {}", src_.origin_of(p), p, to_text(v), err);
    }
  }

  const ConfigSource& src_;
  YAML::Node node_;
  std::string path_;
  std::vector<std::string> known_;
};

// ---------------------------------------------------------------- writer

class Writer : public FieldVisitor {
 public:
  explicit Writer(YAML::Emitter& e) : e_(e) {}
#define MC_WRITE(T) \
  void field(const char* name, T& v, const char*, const Check<T>&) override { write(name, v); }
  MC_FIELD_TYPES(MC_WRITE)
#undef MC_WRITE
  void section(const char* name, Config& c, const char*) override {
    if (c.omitted_from_dump()) return;
    e_ << YAML::Key << name << YAML::Value << YAML::BeginMap;
    c.visit(*this);
    e_ << YAML::EndMap;
  }
  void component(const char* name, Component& c, const char*) override {
    e_ << YAML::Key << name << YAML::Value << YAML::BeginMap;
    e_ << YAML::Key << "type" << YAML::Value << c.type;
    if (c.cfg) c.cfg->visit(*this);
    e_ << YAML::EndMap;
  }

 private:
  template <class T>
  void write(const char* name, const T& v) {
    e_ << YAML::Key << name << YAML::Value;
    if constexpr (std::is_same_v<T, std::vector<std::string>>) {
      e_ << YAML::Flow << YAML::BeginSeq;
      for (auto& x : v) e_ << YAML::DoubleQuoted << x;
      e_ << YAML::EndSeq;
    } else if constexpr (std::is_same_v<T, std::string>) {
      e_ << YAML::DoubleQuoted << v;
    } else if constexpr (std::is_same_v<T, std::vector<int>> || std::is_same_v<T, std::vector<double>>) {
      e_ << YAML::Flow << YAML::BeginSeq;
      for (auto& x : v) e_ << to_text(x);
      e_ << YAML::EndSeq;
    } else {
      e_ << to_text(v);
    }
  }
  YAML::Emitter& e_;
};

// ---------------------------------------------------------------- describer

class Describer : public FieldVisitor {
 public:
  Describer(std::string prefix, std::ostringstream& out) : prefix_(std::move(prefix)), out_(out) {}
#define MC_DESCRIBE(T) \
  void field(const char* name, T& v, const char* help, const Check<T>& c) override { line(name, v, help, c.text); }
  MC_FIELD_TYPES(MC_DESCRIBE)
#undef MC_DESCRIBE
  void section(const char* name, Config& c, const char* help) override {
    out_ << fmt::format("\n{}  [section] {}\n", join_path(prefix_, name), help);
    Describer d(join_path(prefix_, name), out_);
    c.visit(d);
  }
  void component(const char* name, Component& c, const char* help) override {
    std::string p = join_path(prefix_, name);
    out_ << fmt::format("\n{}  [component '{}'] {}\n", p, c.family, help);
    auto types = component_types(c.family);
    out_ << fmt::format("  {:<34} {:<14} {:<18} one of {}\n", p + ".type", "string", c.type,
                        fmt::join(types, "|"));
    for (auto& t : types) {
      auto cfg = make_component_config(c.family, t);
      out_ << fmt::format("  -- with type: {}  ({})\n", t, component_help(c.family, t));
      Describer d(p, out_);
      cfg->visit(d);
    }
  }

 private:
  template <class T>
  void line(const char* name, const T& v, const char* help, const std::string& rule) {
    out_ << fmt::format("  {:<34} {:<14} {:<18} {}{}\n", join_path(prefix_, name), type_name<T>(), to_text(v), help,
                        rule.empty() ? "" : " [" + rule + "]");
  }
  std::string prefix_;
  std::ostringstream& out_;
};

// Finds a named section to describe on its own.
class SectionFinder : public FieldVisitor {
 public:
  explicit SectionFinder(std::string want) : want_(std::move(want)) {}
#define MC_SKIP(T) \
  void field(const char*, T&, const char*, const Check<T>&) override {}
  MC_FIELD_TYPES(MC_SKIP)
#undef MC_SKIP
  void section(const char* name, Config& c, const char* help) override {
    if (want_ == name) {
      Describer d("", out);
      d.section(name, c, help);
      found = true;
    }
  }
  void component(const char* name, Component& c, const char* help) override {
    if (want_ == name) {
      Describer d("", out);
      d.component(name, c, help);
      found = true;
    }
  }
  std::vector<std::string> names;
  std::ostringstream out;
  bool found = false;

 private:
  std::string want_;
};

class NameCollector : public FieldVisitor {
 public:
#define MC_NAME(T) \
  void field(const char*, T&, const char*, const Check<T>&) override {}
  MC_FIELD_TYPES(MC_NAME)
#undef MC_NAME
  void section(const char* name, Config&, const char*) override { names.push_back(name); }
  void component(const char* name, Component&, const char*) override { names.push_back(name); }
  std::vector<std::string> names;
};

}  // namespace

void parse_config(const ConfigSource& src, Config& cfg) {
  Reader::read_section(src, *src.root, "", cfg);
}

std::string dump_config(Config& cfg) {
  YAML::Emitter e;
  e << YAML::BeginMap;
  Writer w(e);
  cfg.visit(w);
  e << YAML::EndMap;
  return std::string(e.c_str()) + "\n";
}

std::string describe_config(Config& cfg, const std::string& only_section) {
  if (!only_section.empty()) {
    SectionFinder f(only_section);
    cfg.visit(f);
    if (!f.found) {
      NameCollector n;
      cfg.visit(n);
      fail("no config section '{}'{}; sections: {}", only_section, hint_suffix(only_section, n.names),
           fmt::format("{}", fmt::join(n.names, ", ")));
    }
    return f.out.str();
  }
  std::ostringstream out;
  out << fmt::format("  {:<34} {:<14} {:<18} {}\n", "key", "type", "default", "meaning [rule]");
  Describer d("", out);
  cfg.visit(d);
  return out.str();
}

std::string parse_component_file(const std::string& file, const std::string& key,
                                 const std::vector<std::string>& substitutions,
                                 const std::vector<std::string>& overrides, Component& out) {
  ConfigSource plain = compose_config(file, {});
  std::vector<std::string> applied;
  for (const auto& s : substitutions) {
    auto eq = s.find('=');
    if (eq == std::string::npos) fail("substitution '{}' is not path=value", s);
    std::string p = s.substr(0, eq);
    YAML::Node n = YAML::Clone(*plain.root);
    bool exists = true;
    size_t start = 0;
    while (exists) {
      size_t dot = p.find('.', start);
      std::string part = p.substr(start, dot == std::string::npos ? std::string::npos : dot - start);
      if (!n.IsMap() || !n[part]) {
        exists = false;
        break;
      }
      n.reset(n[part]);
      if (dot == std::string::npos) break;
      start = dot + 1;
    }
    if (exists) applied.push_back(s);
  }
  for (const auto& o : overrides) applied.push_back(o);
  struct Wrapper : Config {
    Component* c;
    std::string key;
    void visit(FieldVisitor& v) override { v(key.c_str(), *c, "component"); }
  } w;
  w.c = &out;
  w.key = key;
  parse_config(compose_config(file, applied), w);
  return dump_config(w);
}

bool configs_equal(Config& a, Config& b) { return dump_config(a) == dump_config(b); }

std::string config_hash(Config& cfg) {
  uint64_t h = 1469598103934665603ull;
  for (unsigned char ch : dump_config(cfg)) h = (h ^ ch) * 1099511628211ull;
  return fmt::format("{:012x}", h & 0xffffffffffffull);
}

}  // namespace mc
