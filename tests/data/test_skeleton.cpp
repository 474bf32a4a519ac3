// Skeleton as data: graph matrices, rest pose, forward kinematics, and load errors.
#include <catch2/catch.hpp>

#include <Eigen/Eigenvalues>
#include <random>

#include "core/error.h"
#include "data/skeleton.h"
#include "test_util.h"

using mc::test::user_error_of;

namespace {

const mc::Skeleton& skel() { return mc::humanml3d_skeleton(); }

// Random rotation from a normalised 4-vector of normals (uniform on SO(3)).
Eigen::Matrix3d random_rotation(std::mt19937_64& gen) {
  auto normal = [&] {  // Box-Muller from raw bits: same numbers on every standard library
    double u1 = 1.0 - (gen() >> 11) * 0x1.0p-53, u2 = (gen() >> 11) * 0x1.0p-53;
    return std::sqrt(-2 * std::log(u1)) * std::cos(2 * M_PI * u2);
  };
  Eigen::Quaterniond q(normal(), normal(), normal(), normal());
  return q.normalized().toRotationMatrix();
}

std::string skeleton_yaml_with(const std::string& joints) {
  return "name: tiny\njoints:\n" + joints;
}

}  // namespace

TEST_CASE("skeleton file loads as the HumanML3D 22-joint tree", "[skeleton]") {
  const auto& s = skel();
  REQUIRE(s.num_joints() == 22);
  CHECK(s.joint_names[0] == "pelvis");
  CHECK(s.parents[21] == 19);
  CHECK(s.joint_index("l_wrist") == 20);
  CHECK(s.role("face") == std::vector<int>{2, 1, 17, 16});
  CHECK(s.bone_lengths[1] == Approx(0.10307));
  CHECK(s.bone_lengths[21] == Approx(0.26988));
}

TEST_CASE("laplacian rows sum to zero and it is symmetric PSD with one zero eigenvalue", "[skeleton]") {
  Eigen::MatrixXd L = skel().laplacian();
  REQUIRE(L.rows() == 22);
  CHECK(L.rowwise().sum().cwiseAbs().maxCoeff() == 0.0);
  CHECK((L - L.transpose()).cwiseAbs().maxCoeff() == 0.0);
  // Diagonal = number of neighbours: spine3 (9) has spine2, neck and both collars.
  CHECK(L(9, 9) == 4.0);
  CHECK(L(0, 0) == 3.0);
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(L);
  CHECK(eig.eigenvalues().minCoeff() > -1e-9);
  int zeros = 0;
  for (int k = 0; k < 22; ++k) zeros += std::abs(eig.eigenvalues()(k)) < 1e-9;
  CHECK(zeros == 1);  // a connected tree
}

TEST_CASE("rest pose has the file's bone lengths, left joints on +X, head up", "[skeleton]") {
  const auto& s = skel();
  auto rest = s.rest_pose();
  CHECK(rest[0].norm() == 0.0);
  for (int j = 1; j < s.num_joints(); ++j)
    CHECK((rest[j] - rest[s.parents[j]]).norm() == Approx(s.bone_lengths[j]).margin(1e-12));
  for (const char* n : {"hip", "knee", "ankle", "foot", "collar", "shoulder", "elbow", "wrist"}) {
    CHECK(rest[s.joint_index(std::string("l_") + n)].x() > 0);
    CHECK(rest[s.joint_index(std::string("r_") + n)].x() < 0);
  }
  CHECK(rest[s.joint_index("head")].y() > rest[s.joint_index("neck")].y() - 1e-12);
  CHECK(rest[s.joint_index("l_ankle")].y() < -0.8);
}

TEST_CASE("FK of identity rotations is the rest pose moved to the root", "[skeleton]") {
  const auto& s = skel();
  std::vector<Eigen::Matrix3d> id(s.num_joints(), Eigen::Matrix3d::Identity());
  Eigen::Vector3d root(0.3, 0.9, -1.2);
  auto pos = s.forward_kinematics(root, id);
  auto rest = s.rest_pose();
  for (int j = 0; j < s.num_joints(); ++j) CHECK((pos[j] - (rest[j] + root)).norm() < 1e-12);
}

TEST_CASE("FK keeps bone lengths under random rotations and follows the parent chain", "[skeleton]") {
  const auto& s = skel();
  std::mt19937_64 gen(7);
  for (int trial = 0; trial < 20; ++trial) {
    std::vector<Eigen::Matrix3d> rot(s.num_joints());
    for (auto& r : rot) r = random_rotation(gen);
    auto pos = s.forward_kinematics(Eigen::Vector3d(trial, 0, 0), rot);
    for (int j = 1; j < s.num_joints(); ++j)
      CHECK((pos[j] - pos[s.parents[j]]).norm() == Approx(s.bone_lengths[j]).margin(1e-12));
    // HumanML3D convention: bone j is the rest direction turned by the product of
    // local rotations from the root down to j.
    int j = s.joint_index("r_wrist");
    Eigen::Matrix3d g = Eigen::Matrix3d::Identity();
    std::vector<int> chain;
    for (int k = j; k >= 0; k = s.parents[k]) chain.insert(chain.begin(), k);
    for (int k : chain) g = g * rot[k];
    Eigen::Vector3d bone = g * s.rest_directions[j] * s.bone_lengths[j];
    CHECK((pos[j] - pos[s.parents[j]] - bone).norm() < 1e-12);
  }
}

TEST_CASE("skeleton YAML round-trips", "[skeleton]") {
  const auto& s = skel();
  mc::Skeleton back = mc::skeleton_from_yaml_text(mc::skeleton_to_yaml(s), "<roundtrip>");
  CHECK(back == s);
  back.bone_lengths[4] += 0.01;
  CHECK_FALSE(back == s);
}

TEST_CASE("skeleton errors are user errors that name the problem", "[skeleton]") {
  const auto& s = skel();
  CHECK_THAT(user_error_of([&] { s.joint_index("l_elbw"); }), Catch::Matchers::Contains("did you mean 'l_elbow'"));
  CHECK_THAT(user_error_of([&] { s.role("toe"); }), Catch::Matchers::Contains("did you mean 'toes'"));
  // A parent listed after its child.
  CHECK_THAT(user_error_of([&] { mc::skeleton_from_yaml_text(skeleton_yaml_with(
                                                       "  - {name: root, parent: -1, direction: [0,0,0], length: 0}\n"
                                                       "  - {name: a, parent: 2, direction: [0,1,0], length: 1}\n"
                                                       "  - {name: b, parent: 0, direction: [0,1,0], length: 1}\n"),
                                                   "tiny.yaml"); }), Catch::Matchers::Contains("parents must precede"));
  CHECK_THAT(user_error_of([&] { mc::skeleton_from_yaml_text(skeleton_yaml_with(
                                                       "  - {name: root, parent: -1, direction: [0,0,0], length: 0}\n"
                                                       "  - {name: a, parent: 0, direction: [0,1,0]}\n"),
                                                   "tiny.yaml"); }), Catch::Matchers::Contains("lacks key 'length'"));
  CHECK_THAT(user_error_of([&] { mc::skeleton_from_yaml_text(skeleton_yaml_with(
                                                       "  - {name: root, parent: -1, direction: [0,0,0], length: 0}\n"
                                                       "  - {name: a, parent: 0, direction: [0,2,0], length: 1}\n"),
                                                   "tiny.yaml"); }), Catch::Matchers::Contains("not a unit vector"));
  CHECK_THROWS_AS(mc::load_skeleton("configs/skeletons/no_such_skeleton.yaml"), mc::UserError);
}
