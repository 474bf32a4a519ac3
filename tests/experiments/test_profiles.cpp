// Profiles are self-consistent: under every configs/profile/*.yaml, each component
// the table replay would train (the profile's evaluator, and every training config
// reachable from the generators and protocols of every experiment spec, after the
// profile's substitutions, row overrides and trained_configs redirects, following
// training configs named inside training configs) reads the profile's own data.
// Nothing is trained: the configs are composed and walked.
#include <catch2/catch.hpp>

#include <yaml-cpp/yaml.h>

#include <functional>
#include <map>
#include <set>

#include "core/error.h"
#include "data/skeleton.h"
#include "experiments/experiment.h"
#include "experiments/reproduce.h"
#include "test_util.h"
#include "train/train_job.h"
#include "train/trainer.h"

using namespace mc;

namespace {

bool ends_with(const std::string& s, const std::string& tail) {
  return s.size() >= tail.size() && s.compare(s.size() - tail.size(), tail.size(), tail) == 0;
}

std::string canonical(const std::string& path) {
  return fs::weakly_canonical(fs::path(resolve_data_path(path))).string();
}

// A config file that `run_train` can take: it composes into a document with model
// and optim sections (fixture, protocol and generator files have neither).
bool is_training_config(const std::string& file) {
  const std::string path = resolve_data_path(file);
  if (!fs::is_regular_file(path)) return false;
  ConfigSource src = compose_config(path, {});
  return (*src.root)["model"] && (*src.root)["optim"];
}

// A training config named somewhere in a resolved config, with the overrides the
// code passes along with it.
struct Reference {
  std::string file;
  std::vector<std::string> overrides;
  std::string where;  // how it was reached, for messages
};

// Every string that names a training config in `node`. The codebase's convention:
// `config` sits next to `overrides` and `run_dir`, `<x>_config` next to
// `<x>_overrides` and `<x>_run`; a non-empty run means nothing is trained there.
// `origin` says where the document came from, `path` is the key path inside it.
void find_references(const YAML::Node& node, const std::string& origin, const std::string& path,
                     std::vector<Reference>& out) {
  if (node.IsSequence()) {
    for (size_t i = 0; i < node.size(); ++i) find_references(node[i], origin, fmt::format("{}[{}]", path, i), out);
    return;
  }
  if (!node.IsMap()) return;
  for (auto it = node.begin(); it != node.end(); ++it) {
    const std::string key = it->first.as<std::string>();
    const std::string here = path.empty() ? key : path + "." + key;
    const YAML::Node& value = it->second;
    if (!value.IsScalar()) {
      find_references(value, origin, here, out);
      continue;
    }
    const std::string s = value.as<std::string>();
    if (!ends_with(s, ".yaml") || !is_training_config(s)) continue;
    const bool plain = key == "config";
    if (!plain && !ends_with(key, "_config"))
      FAIL(origin << here << " names the training config " << s
                << " under a key that is neither `config` nor `<x>_config`: this test (and the reader) cannot tell "
                   "its overrides");
    const std::string prefix = plain ? "" : key.substr(0, key.size() - std::string("_config").size());
    const std::string run_key = plain ? "run_dir" : prefix + "_run";
    const std::string ov_key = plain ? "overrides" : prefix + "_overrides";
    if (node[run_key] && node[run_key].IsScalar() && !node[run_key].as<std::string>().empty()) continue;
    Reference r{s, {}, origin + here};
    if (node[ov_key]) r.overrides = node[ov_key].as<std::vector<std::string>>();
    out.push_back(std::move(r));
  }
}

struct Trained {
  std::string file;  // after the redirect
  std::string where;
  std::string data, fixture, model_type;
};

// Everything the profile would train, reached from the table specs and its evaluator.
std::vector<Trained> trained_components(const std::string& profile_file) {
  ProfileFile pf = load_job<ProfileFile>(profile_file, {});
  set_config_redirects(pf.profile.trained_configs, profile_file + ": profile.trained_configs");
  std::vector<Reference> todo;
  todo.push_back({pf.profile.evaluator, {}, "profile.evaluator"});
  for (const auto& spec_file : list_table_specs("experiments")) {
    TableSpec spec = load_table_spec(spec_file);
    for (const auto& row : spec.rows) {
      ResolvedRow r = resolve_row(pf.profile, spec, row);
      const std::string where = spec.table.id + " / " + row.id;
      find_references(YAML::Load(r.generator_yaml), where + ": ", "", todo);
      find_references(YAML::Load(r.protocol_yaml), where + ": ", "", todo);
    }
  }
  std::vector<Trained> out;
  std::set<std::string> seen;
  while (!todo.empty()) {
    Reference ref = todo.back();
    todo.pop_back();
    const std::string file = redirected_config(resolve_data_path(ref.file));
    std::string key = canonical(file);
    for (auto& o : ref.overrides) key += "\n" + o;
    if (!seen.insert(key).second) continue;
    auto job = load_job<TrainJobConfig>(file, ref.overrides);
    const std::string where = ref.where + " -> " + file;
    out.push_back({file, where, job.data.path, job.data.fixture, job.model.type});
    find_references(YAML::Load(dump_config(job)), where + ": ", "", todo);
  }
  set_config_redirects({}, "");
  return out;
}

}  // namespace

TEST_CASE("profiles: every component a profile trains reads the profile's own data", "[profile]") {
  std::vector<std::string> profiles;
  for (auto& e : fs::directory_iterator(resolve_data_path("configs/profile")))
    if (e.path().extension() == ".yaml") profiles.push_back(e.path().string());
  std::sort(profiles.begin(), profiles.end());
  REQUIRE(profiles.size() >= 3);  // smoke, standard, paper at least
  for (const auto& file : profiles) {
    ProfileFile pf = load_job<ProfileFile>(file, {});
    std::vector<Trained> trained = trained_components(file);
    std::set<std::string> types;
    for (const auto& t : trained) {
      INFO("profile " << file << "\ncomponent " << t.where);
      types.insert(t.model_type);
      CHECK(canonical(t.data) == canonical(pf.profile.data));
      // Two recipes for one data file would make its contents depend on who built it first.
      if (!t.fixture.empty() && !pf.profile.data_fixture.empty())
        CHECK(canonical(t.fixture) == canonical(pf.profile.data_fixture));
    }
    // The walk reaches the specs' components (a walker that found nothing would pass trivially).
    INFO("profile " << file);
    for (const char* type : {"t2m_evaluator", "flow_prior", "flow_controlnet", "vq_tokenizer", "tmd_prior",
                             "masked_prior", "anchor_adapter"})
      CHECK(types.count(type) == 1);
  }
}

// profile.table_num_samples: a profile gives one table more tasks per row without the
// table's spec (which the smoke and CI profiles share) changing; malformed entries
// fail at load, naming the entry.
TEST_CASE("profiles: table_num_samples picks one table's tasks per row", "[profile]") {
  ProfileConfig p;
  p.num_samples = 32;
  TableConfig a, b;
  a.id = "anchorroute/table4";
  b.id = "projflow/table3";
  CHECK(table_tasks(p, a) == 32);
  b.num_samples = 48;  // the table's own count beats the profile's
  CHECK(table_tasks(p, b) == 48);
  p.table_num_samples = {"anchorroute/table4=256", "projflow/table3=64"};
  CHECK(p.validate().empty());
  CHECK(table_tasks(p, a) == 256);
  CHECK(table_tasks(p, b) == 64);  // the profile's entry beats the table's
  TableConfig c;
  c.id = "anchorroute/table5";
  CHECK(table_tasks(p, c) == 32);
  for (const char* bad : {"anchorroute/table4", "anchorroute/table4=", "=12", "anchorroute/table4=0",
                          "anchorroute/table4=-3", "anchorroute/table4=1e3"}) {
    INFO(bad);
    p.table_num_samples = {bad};
    CHECK_THAT(p.validate(), Catch::Contains(bad) && Catch::Contains("table_id=N"));
  }
  p.table_num_samples = {"anchorroute/table4=8", "anchorroute/table4=16"};
  CHECK_THAT(p.validate(), Catch::Contains("listed twice"));
  // The standard profile's entries name tables that exist and load.
  ProfileFile pf = load_job<ProfileFile>(resolve_data_path("configs/profile/standard.yaml"), {});
  CHECK(table_tasks(pf.profile, a) == 256);
  TableSpec t4 = load_table_spec(resolve_data_path("experiments/anchorroute/table4.yaml"));
  CHECK(table_tasks(pf.profile, t4.table) == 256);
}
