// Skeleton loading/validation (YAML), graph matrices and forward kinematics.
#include "data/skeleton.h"

#include <yaml-cpp/yaml.h>

#include <filesystem>

#include "core/atomic_file.h"
#include "core/config.h"
#include "core/error.h"
#include "core/yaml_strict.h"
#include "core/source_dir.h"

namespace mc {
namespace fs = std::filesystem;

int Skeleton::joint_index(const std::string& joint_name) const {
  for (int j = 0; j < num_joints(); ++j)
    if (joint_names[j] == joint_name) return j;
  std::string hint = did_you_mean(joint_name, joint_names);
  fail("skeleton '{}' has no joint '{}'{}", name, joint_name, hint.empty() ? "" : " (did you mean '" + hint + "'?)");
}

const std::vector<int>& Skeleton::role(const std::string& role_name) const {
  auto it = roles.find(role_name);
  if (it == roles.end()) {
    std::vector<std::string> names;
    for (auto& [k, _] : roles) names.push_back(k);
    std::string hint = did_you_mean(role_name, names);
    fail("skeleton '{}' defines no joint role '{}'{}; add it under roles: in the skeleton file", name, role_name,
         hint.empty() ? "" : " (did you mean '" + hint + "'?)");
  }
  return it->second;
}

Eigen::MatrixXd Skeleton::adjacency() const {
  const int J = num_joints();
  Eigen::MatrixXd a = Eigen::MatrixXd::Zero(J, J);
  for (int j = 0; j < J; ++j)
    if (parents[j] >= 0) a(j, parents[j]) = a(parents[j], j) = 1.0;
  return a;
}

Eigen::MatrixXd Skeleton::laplacian() const {
  Eigen::MatrixXd a = adjacency();
  Eigen::MatrixXd d = a.rowwise().sum().asDiagonal();
  return d - a;
}

std::vector<Eigen::Vector3d> Skeleton::rest_pose() const {
  std::vector<Eigen::Matrix3d> identity(num_joints(), Eigen::Matrix3d::Identity());
  return forward_kinematics(Eigen::Vector3d::Zero(), identity);
}

// HumanML3D convention: global[j] = global[parent] * local[j];
// pos[j] = pos[parent] + global[j] * (direction[j] * length[j]).
std::vector<Eigen::Vector3d> Skeleton::forward_kinematics(const Eigen::Vector3d& root_position,
                                                          const std::vector<Eigen::Matrix3d>& local) const {
  const int J = num_joints();
  std::vector<Eigen::Vector3d> pos(J);
  std::vector<Eigen::Matrix3d> global(J);
  for (int j = 0; j < J; ++j) {
    int p = parents[j];
    if (p < 0) {
      global[j] = local[j];
      pos[j] = root_position;
    } else {
      global[j] = global[p] * local[j];
      pos[j] = pos[p] + global[j] * (rest_directions[j] * bone_lengths[j]);
    }
  }
  return pos;
}

void Skeleton::validate(const std::string& source) const {
  const size_t J = parents.size();
  if (J == 0) fail("{}: skeleton has no joints", source);
  if (joint_names.size() != J || rest_directions.size() != J || bone_lengths.size() != J)
    fail("{}: skeleton arrays disagree in length (names {}, parents {}, directions {}, lengths {})", source,
         joint_names.size(), J, rest_directions.size(), bone_lengths.size());
  if (parents[0] != -1) fail("{}: joint 0 ('{}') must be the root (parent -1)", source, joint_names[0]);
  for (size_t j = 1; j < J; ++j) {
    if (parents[j] < 0 || parents[j] >= static_cast<int>(j))
      fail("{}: joint {} ('{}') has parent {}; parents must precede their children", source, j, joint_names[j],
           parents[j]);
    if (std::abs(rest_directions[j].norm() - 1.0) > 1e-6)
      fail("{}: joint {} ('{}') rest direction is not a unit vector", source, j, joint_names[j]);
    if (!(bone_lengths[j] > 0)) fail("{}: joint {} ('{}') bone length must be > 0", source, j, joint_names[j]);
  }
  for (auto& [role_name, idx] : roles)
    for (int j : idx)
      if (j < 0 || j >= static_cast<int>(J))
        fail("{}: role '{}' names joint {}, outside 0..{}", source, role_name, j, J - 1);
  for (auto& chain : chains)
    for (int j : chain)
      if (j < 0 || j >= static_cast<int>(J)) fail("{}: chain names joint {}, outside 0..{}", source, j, J - 1);
}

bool Skeleton::operator==(const Skeleton& o) const {
  if (name != o.name || joint_names != o.joint_names || parents != o.parents || chains != o.chains ||
      roles != o.roles || bone_lengths.size() != o.bone_lengths.size())
    return false;
  for (size_t j = 0; j < bone_lengths.size(); ++j)
    if (std::abs(bone_lengths[j] - o.bone_lengths[j]) > 1e-9 ||
        (rest_directions[j] - o.rest_directions[j]).norm() > 1e-9)
      return false;
  return true;
}

Skeleton skeleton_from_yaml_text(const std::string& text, const std::string& source) {
  YAML::Node root = parse_yaml_strict(text, source, "skeleton YAML");
  Skeleton s;
  try {
    if (!root.IsMap() || !root["joints"] || !root["joints"].IsSequence())
      fail("{}: a skeleton file needs 'name' and a 'joints' list", source);
    s.name = root["name"] ? root["name"].as<std::string>() : fs::path(source).stem().string();
    int idx = 0;
    for (auto j : root["joints"]) {
      for (const char* key : {"name", "parent", "direction", "length"})
        if (!j[key]) fail("{}: joints[{}] lacks key '{}'", source, idx, key);
      s.joint_names.push_back(j["name"].as<std::string>());
      s.parents.push_back(j["parent"].as<int>());
      auto d = j["direction"].as<std::vector<double>>();
      if (d.size() != 3) fail("{}: joints[{}].direction must have 3 numbers", source, idx);
      s.rest_directions.emplace_back(d[0], d[1], d[2]);
      s.bone_lengths.push_back(j["length"].as<double>());
      ++idx;
    }
    if (root["chains"]) s.chains = root["chains"].as<std::vector<std::vector<int>>>();
    if (root["roles"])
      for (auto kv : root["roles"]) s.roles[kv.first.as<std::string>()] = kv.second.as<std::vector<int>>();
  } catch (const YAML::Exception& e) {
    fail("{}:{}: bad value in skeleton file: {}", source, e.mark.line + 1, e.msg);
  }
  s.validate(source);
  return s;
}

std::string skeleton_to_yaml(const Skeleton& s) {
  YAML::Emitter e;
  e << YAML::BeginMap << YAML::Key << "name" << YAML::Value << s.name;
  e << YAML::Key << "joints" << YAML::Value << YAML::BeginSeq;
  for (int j = 0; j < s.num_joints(); ++j) {
    e << YAML::Flow << YAML::BeginMap;
    e << YAML::Key << "name" << YAML::Value << s.joint_names[j];
    e << YAML::Key << "parent" << YAML::Value << s.parents[j];
    e << YAML::Key << "direction" << YAML::Value << YAML::Flow << YAML::BeginSeq;
    for (int a = 0; a < 3; ++a) e << fmt::format("{}", s.rest_directions[j][a]);
    e << YAML::EndSeq;
    e << YAML::Key << "length" << YAML::Value << fmt::format("{}", s.bone_lengths[j]);
    e << YAML::EndMap;
  }
  e << YAML::EndSeq;
  e << YAML::Key << "chains" << YAML::Value << YAML::Flow << s.chains;
  e << YAML::Key << "roles" << YAML::Value << YAML::BeginMap;
  for (auto& [k, v] : s.roles) e << YAML::Key << k << YAML::Value << YAML::Flow << v;
  e << YAML::EndMap << YAML::EndMap;
  return std::string(e.c_str()) + "\n";
}

std::string resolve_data_path(const std::string& path) {
  if (path.empty() || fs::path(path).is_absolute() || fs::exists(path)) return path;
  fs::path in_source = fs::path(source_dir()) / path;
  if (fs::exists(in_source)) return in_source.string();
  return path;
}

Skeleton load_skeleton(const std::string& path) {
  std::string p = resolve_data_path(path);
  return skeleton_from_yaml_text(read_file(p), path);
}

const Skeleton& humanml3d_skeleton() {
  static const Skeleton s = load_skeleton("configs/skeletons/humanml3d22.yaml");
  return s;
}

}  // namespace mc
