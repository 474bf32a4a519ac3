// A skeleton as data: joint names, parents, rest directions, bone lengths,
// chains and semantic roles, loaded from a YAML file (configs/skeletons/) and
// stored inside every motion file. Nothing else hard-codes the joint count.
#pragma once
#include <Eigen/Dense>
#include <map>
#include <string>
#include <vector>

namespace mc {

struct Skeleton {
  std::string name;
  std::vector<std::string> joint_names;         // J
  std::vector<int> parents;                     // J, -1 for the root
  std::vector<Eigen::Vector3d> rest_directions; // J unit vectors (root: zero)
  std::vector<double> bone_lengths;             // J metres, length of the bone to the parent (root: 0)
  std::vector<std::vector<int>> chains;         // kinematic chains from the root outwards
  // Named joint groups, e.g. "toes" -> {10, 11}, "face" -> {2, 1, 17, 16}
  // (r_hip, l_hip, r_shoulder, l_shoulder), "left_foot" -> {7, 10}, "right_foot" -> {8, 11},
  // "lower_body", "upper_body", "left_hand", "right_hand".
  std::map<std::string, std::vector<int>> roles;

  int num_joints() const { return static_cast<int>(parents.size()); }
  int root() const { return 0; }
  int joint_index(const std::string& joint_name) const;           // UserError with "did you mean"
  const std::vector<int>& role(const std::string& role_name) const;  // UserError if absent

  Eigen::MatrixXd adjacency() const;  // J x J, 1 where parent-child
  Eigen::MatrixXd laplacian() const;  // D - A (unnormalised graph Laplacian)
  // Joint positions of the rest pose with the root at the origin.
  std::vector<Eigen::Vector3d> rest_pose() const;

  // Forward kinematics for one frame: global rotation of each joint's frame
  // (`global_rot[j]` orients the bone from parent(j) to j, i.e. child offset =
  // global_rot[parent] * rest_dir * length) and root position. Returns J positions.
  std::vector<Eigen::Vector3d> forward_kinematics(const Eigen::Vector3d& root_position,
                                                   const std::vector<Eigen::Matrix3d>& local_rotations) const;

  void validate(const std::string& source) const;  // parents precede children, sizes agree, unit dirs
  bool operator==(const Skeleton& o) const;
};

Skeleton load_skeleton(const std::string& path);    // YAML file; UserError naming file/key
std::string skeleton_to_yaml(const Skeleton& s);
Skeleton skeleton_from_yaml_text(const std::string& text, const std::string& source);
// Resolves a path relative to the cwd, then to the source tree (for installed defaults).
std::string resolve_data_path(const std::string& path);
// The HumanML3D 22-joint skeleton from configs/skeletons/humanml3d22.yaml.
const Skeleton& humanml3d_skeleton();

}  // namespace mc
