// BVH (Biovision hierarchy) out and in: joint positions on a skeleton become a
// BVH whose rest offsets are the skeleton's bones and whose per-frame rotations
// are solved from the positions; a small reader and forward kinematics check the
// round trip (docs/formats.md, "BVH export").
#pragma once
#include <Eigen/Dense>
#include <string>
#include <vector>

#include "data/skeleton.h"

namespace mc {

struct BvhOptions {
  // Which joints carry translation channels:
  //   "root": only the root (a standard rigid BVH; exact when the clip keeps the
  //           skeleton's bone lengths and the shape of its multi-child joints);
  //   "all":  every joint, holding its per-frame offset from its parent, so forward
  //           kinematics returns the input exactly whatever the bone lengths;
  //   "auto": "root" when its forward kinematics stays within `tolerance` of the
  //           input, otherwise "all" (generated motion, whose bones drift).
  std::string translations = "auto";
  double tolerance = 1e-4;  // metres, for "auto"
  double scale = 1.0;       // file units per metre (100 = centimetres)
};

// What positions alone fix and what they do not: the swing of every bone with one
// child, the best-fit rotation of joints with several children, the root's
// translation. Twist about a one-child bone, and the roll of leaf joints (head,
// hands, toes), are not observable and are written as zero.
struct BvhExport {
  std::string text;          // the BVH file
  bool all_translations = false;
  double rigid_error = 0.0;  // largest |FK - input| (m) of the root-translation-only solution
  double written_error = 0.0;  // largest |FK - input| (m) of the text as written (re-read, rounded)
};

// One clip [frames, J, 3] (metres, Y up) on `skel` at `fps`. UserError when the
// options are invalid or the clip is empty or not finite.
BvhExport clip_to_bvh(const Skeleton& skel, const float* joints, int frames, double fps, const BvhOptions& opt = {});

// A parsed BVH: joints in file order (parents first), their rest offsets and
// channels, and the motion block.
struct BvhMotion {
  std::vector<std::string> names;
  std::vector<int> parents;                   // -1 for the root
  std::vector<Eigen::Vector3d> offsets;       // rest offset from the parent (root: its rest position)
  std::vector<std::vector<std::string>> channels;  // per joint, e.g. {"Zrotation", "Xrotation", "Yrotation"}
  std::vector<Eigen::Vector3d> end_sites;     // per joint: End Site offset (NaN when none)
  int frames = 0;
  double frame_time = 0.0;
  std::vector<double> values;                 // [frames, total channels], in the file's units and degrees
  int num_channels() const;
};

BvhMotion parse_bvh(const std::string& text, const std::string& source);  // UserError naming source and line

// Joint positions [frames, J, 3] of every frame, divided by `scale` (file units per
// metre). A joint with position channels takes them as its whole local
// translation (its OFFSET is only the rest pose), as Blender's importer reads them.
std::vector<double> bvh_positions(const BvhMotion& m, double scale = 1.0);

// Euler angles (radians) of R = Rz(z) Rx(x) Ry(y), the BVH channel order
// "Zrotation Xrotation Yrotation", chosen among the equivalent triples to lie
// nearest to `previous` (angle unwrapping across frames). Returned as (z, x, y).
Eigen::Vector3d euler_zxy_nearest(const Eigen::Matrix3d& R, const Eigen::Vector3d& previous);
Eigen::Matrix3d rotation_zxy(const Eigen::Vector3d& zxy);

}  // namespace mc
