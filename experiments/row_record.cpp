// A table row's record of the weights it was computed with (dependencies.yaml in its
// run directory) and the check that decides whether a finished row is reused,
// adopted (a legacy row) or recomputed in place.
#include "experiments/row_record.h"

#include <fmt/format.h>
#include <fmt/ranges.h>

#include <algorithm>
#include <fstream>

#include "core/error.h"
#include "train/dependencies.h"
#include "train/train_job.h"

namespace mc {

namespace {

std::string short_sha(const std::string& sha) { return sha.empty() ? "(no final.pt)" : sha.substr(0, 12); }

bool same_run(const std::string& a, const std::string& b) { return run_key(a) == run_key(b); }

bool lists_run(const std::vector<ResolvedDependency>& deps, const std::string& run) {
  return std::any_of(deps.begin(), deps.end(), [&](const ResolvedDependency& d) { return same_run(d.run, run); });
}

}  // namespace

RowComponents resolve_row_components(Component& generator) {
  take_trained_runs();  // runs noted before (the evaluator's) are not this row's
  const std::vector<ResolvedDependency> direct = resolve_dependencies(generator, nullptr);
  RowComponents out;
  out.trained = take_trained_runs();
  for (const auto& dir : out.trained) {
    auto it = std::find_if(direct.begin(), direct.end(), [&](const ResolvedDependency& d) { return same_run(d.run, dir); });
    if (it != direct.end()) {
      out.all.push_back(*it);
      out.all.back().run = dir;
    } else {
      // A dependency of one of the generator's components (a TMD's tokenizer): named
      // by its experiment folder, its config is in its own run directory.
      out.all.push_back({fs::path(run_key(dir)).parent_path().string(), dir, "", {}, weights_sha1(dir)});
    }
  }
  for (const auto& d : direct)  // named by run directory: used as it is, never trained
    if (!lists_run(out.all, d.run)) out.all.push_back(d);
  return out;
}

ResolvedDependency evaluator_component(const std::string& run_dir, const std::string& config) {
  return {"evaluator", run_dir, config, {}, weights_sha1(run_dir)};
}

std::vector<std::string> read_row_components(const fs::path& row_dir) {
  std::vector<std::string> out;
  std::ifstream in(row_dir / "components.txt");
  for (std::string line; std::getline(in, line);) {
    while (!line.empty() && (line.back() == '\r' || line.back() == ' ')) line.pop_back();
    if (!line.empty()) out.push_back(line);
  }
  return out;
}

RowReuse check_row(const fs::path& row_dir, const RowComponents& now, const ResolvedDependency& evaluator) {
  RowReuse r;
  std::vector<ResolvedDependency> all = now.all;
  all.push_back(evaluator);
  std::optional<std::vector<ResolvedDependency>> recorded;
  try {
    recorded = read_dependency_record(row_dir);
  } catch (const UserError& e) {
    // A cache entry that cannot be trusted is recomputed (which writes a new record).
    r.state = RowReuse::State::recompute;
    r.reasons.push_back(fmt::format("weights its record cannot tell ({})", e.what()));
    return r;
  }
  if (recorded) {
    r.reasons = changed_dependencies(*recorded, all);
    // What changed_dependencies cannot see: a recorded component the row no longer
    // resolves to, unless it was paired by `what` with a new one (named there).
    for (const auto& old : *recorded) {
      if (lists_run(all, old.run)) continue;
      const bool paired = std::any_of(all.begin(), all.end(), [&](const ResolvedDependency& n) {
        return n.what == old.what && !lists_run(*recorded, n.run);
      });
      if (!paired)
        r.reasons.push_back(fmt::format("{} {} {}, which it no longer uses", old.what, old.run, short_sha(old.sha1)));
    }
    r.state = r.reasons.empty() ? RowReuse::State::reuse : RowReuse::State::recompute;
    return r;
  }
  // A legacy row (computed before rows kept a record). Its components.txt lists the
  // generator's own components by path: one of them the row no longer resolves to
  // means the component's config changed since (another run directory).
  std::vector<std::string> now_keys;
  for (const auto& d : now.all) now_keys.push_back(run_key(d.run));
  for (const auto& listed : read_row_components(row_dir))
    if (!lists_run(now.all, listed))
      r.reasons.push_back(fmt::format("{}, which it no longer resolves to (it now uses [{}])", listed,
                                      fmt::join(now_keys, ", ")));
  if (r.reasons.empty()) {
    // Make's rule on the DONE times: a component that finished after the row did was
    // trained again since. The evaluator is left out: its bytes are in the row's key.
    const DependencyCheck c = check_dependencies(row_dir, now.all);
    r.reasons = c.reasons;
    if (c.state == DependencyCheck::State::unrecorded) r.state = RowReuse::State::adopt;
  }
  if (!r.reasons.empty()) r.state = RowReuse::State::recompute;
  return r;
}

void write_row_record(const fs::path& row_dir, const RowComponents& now, const ResolvedDependency& evaluator,
                      const std::string& note) {
  std::vector<ResolvedDependency> all = now.all;
  all.push_back(evaluator);
  write_dependency_record(row_dir, all, note);
}

}  // namespace mc
