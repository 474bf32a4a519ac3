// Evaluation metrics as plain functions over plain data (Eigen matrices and joint
// views): T2M embedding metrics and KID, control errors, foot skating, 2D/3D lifting
// errors, reconstruction MPJPE, motion realism (acceleration, bone-length drift, floor
// penetration) and replication summaries. Torch-free. See docs/metrics.md.
#pragma once
#include <Eigen/Dense>
#include <cstdint>
#include <functional>
#include <map>
#include <random>
#include <string>
#include <vector>

#include "control/camera.h"
#include "data/joints_view.h"
#include "data/motion_set.h"
#include "data/skeleton.h"

namespace mc {

// ---------------------------------------------------------------------------
// Inputs (JointsView and joints_view: data/joints_view.h)
// ---------------------------------------------------------------------------

// Read-only view of a per-entry mask stored as [frames, joints, channels] bytes
// (nonzero = selected). Control masks use channels = 3 (one flag per axis); the
// lifting metrics use channels = 1 (one flag per (frame, joint)).
struct MaskView {
  const uint8_t* data = nullptr;
  int frames = 0;
  int joints = 0;
  int channels = 0;

  bool at(int t, int j, int c = 0) const {
    return data[(static_cast<size_t>(t) * joints + j) * channels + c] != 0;
  }
  bool any(int t, int j) const {
    for (int c = 0; c < channels; ++c)
      if (at(t, j, c)) return true;
    return false;
  }
};
MaskView mask_view(const std::vector<uint8_t>& data, int frames, int joints, int channels,
                   const std::string& what = "mask");

// Embeddings: one row per sample, one column per dimension ([N, D]).
using Embeddings = Eigen::MatrixXd;

// ---------------------------------------------------------------------------
// Deterministic randomness (portable: explicit draws from the engine, no std
// distributions, whose algorithms differ between standard libraries)
// ---------------------------------------------------------------------------

// Uniform integer in [0, n) by rejection sampling (unbiased). n >= 1.
uint64_t uniform_index(std::mt19937_64& rng, uint64_t n);
// k distinct indices from [0, n), in draw order (partial Fisher-Yates). k <= n.
std::vector<int> sample_without_replacement(std::mt19937_64& rng, int n, int k);

// ---------------------------------------------------------------------------
// 1. Embedding metrics (T2M protocol, reference-facts §5)
// ---------------------------------------------------------------------------

struct GaussianStats {
  Eigen::VectorXd mean;  // [D]
  Eigen::MatrixXd cov;   // [D, D], unbiased (divides by N - 1) as numpy.cov
};
GaussianStats gaussian_stats(const Embeddings& x);  // N >= 2

// Principal square root of a symmetric positive semi-definite matrix through its
// eigendecomposition; eigenvalues below zero (rounding) are clamped to zero.
Eigen::MatrixXd sqrtm_psd(const Eigen::MatrixXd& a);

// ||mu1 - mu2||^2 + Tr(C1 + C2 - 2 (C1 C2)^{1/2}).
double frechet_distance(const Eigen::VectorXd& mu1, const Eigen::MatrixXd& cov1,
                        const Eigen::VectorXd& mu2, const Eigen::MatrixXd& cov2);
// Frechet distance of the Gaussians fitted to the two sets (e.g. GT-test vs generated).
double fid(const Embeddings& a, const Embeddings& b);
// Kernel distance (KID, Binkowski et al. 2018): the unbiased estimate of the squared
// MMD between the two sets with the polynomial kernel k(x, y) = (x.y / D + 1)^3, over
// the whole sets (no subset averaging). Unlike FID it has no small-N bias: its
// expectation is 0 for two samples of one distribution, so it can be slightly
// negative. Each set needs >= 2 rows; both the same D.
double kid(const Embeddings& a, const Embeddings& b);

// Row i of `text` is paired with row i of `motion`. Consecutive pools of `pool`
// pairs (a final partial pool is dropped, as the T2M evaluator's drop_last loader
// does); within a pool, text i ranks all pool motions by Euclidean distance (ties
// broken by index) and hits at k if its own motion ranks < k. Returns the
// cumulative hit rates for k = 1..top_k. UserError if there is no full pool.
std::vector<double> r_precision(const Embeddings& text, const Embeddings& motion, int pool = 32,
                                int top_k = 3);
// Mean ||t_i - m_i|| over all rows (MM-Dist). Pass the same rows as r_precision
// covers to reproduce the T2M script (which only sees full batches).
double matching_score(const Embeddings& text, const Embeddings& motion);

// Two independent draws of `pairs` distinct row indices; mean L2 distance between
// the paired rows. UserError if there are fewer than `pairs` rows.
double diversity(const Embeddings& emb, int pairs, std::mt19937_64& rng);
// groups[i] = [G, D] embeddings of G generations for text i (same G for all).
// One pair of draws of `pairs` distinct generation indices shared by all texts (as
// T2M); mean L2 over texts x pairs.
double multimodality(const std::vector<Embeddings>& groups, int pairs, std::mt19937_64& rng);

// ---------------------------------------------------------------------------
// 2. Control metrics (OmniControl; AnchorRoute control error), reference-facts §5
// ---------------------------------------------------------------------------

// One generated sample with its targets. An entry (t, j) is controlled when any of
// its axes is set in `mask`; its error is the Euclidean norm of generated - target
// over the set axes only (a planar-root control masks x and z, never y).
struct ControlSample {
  JointsView generated;  // [T, J, 3]
  JointsView target;     // [T, J, 3]; only masked entries are read
  MaskView mask;         // [T, J, 3]
};

struct ControlOptions {
  std::vector<double> thresholds = {0.5, 0.2};  // metres; the first is the headline one
};

struct ControlThresholdRates {
  double threshold = 0.0;
  double traj_err = 0.0;  // fraction of samples with any entry error > threshold
  double loc_err = 0.0;   // fraction of controlled entries > threshold, per sample, then mean
};

struct ControlMetrics {
  std::vector<ControlThresholdRates> rates;  // one per ControlOptions::thresholds, same order
  double traj_err = 0.0;       // rates[0].traj_err
  double loc_err = 0.0;        // rates[0].loc_err
  double avg_err = 0.0;        // mean entry error per sample, then mean over samples (OmniControl)
  double control_error = 0.0;  // mean entry error over all controlled entries pooled (AnchorRoute)
  int samples = 0;                  // samples with at least one controlled entry (the averages' N)
  int samples_without_control = 0;  // skipped: no controlled entry
  int64_t controlled_entries = 0;
};

// Errors of the controlled entries of one sample, in (frame, joint) order.
std::vector<double> controlled_entry_errors(const ControlSample& s);
ControlMetrics control_metrics(const std::vector<ControlSample>& samples, const ControlOptions& opt = {});
// The same metrics from precomputed per-sample entry errors (e.g. residuals of a
// compiled constraint spec, eval/observation_errors.h).
ControlMetrics control_metrics_from_errors(const std::vector<std::vector<double>>& errors,
                                           const ControlOptions& opt = {});

// ---------------------------------------------------------------------------
// 3. Foot skating ratio (reference-facts §5)
// ---------------------------------------------------------------------------

struct FootSkatingOptions {
  double fps = 20.0;
  double height_threshold = 0.05;     // m, toe height (y) at t and t+1
  double speed_threshold = 0.5;       // m/s, horizontal toe speed at t
  double avg_speed_threshold = 0.5;   // m/s, moving average of the speed at t
  int window = 5;                     // odd; centred, zero padded, divided by `window`
  // false: frames [0, length) of each clip, ratio = count / (length - 1).
  // true: the first `padded_length` stored frames, padding included, ratio =
  // count / (padded_length - 1) (the GMD/OmniControl scripts on 196-frame tensors).
  bool padded_196 = false;
  int padded_length = 196;
};

// Per-transition flags (t -> t+1, size n - 1 over the frames evaluated): 1 if any
// toe skates at t. `toes` are joint indices (the skeleton's "toes" role).
std::vector<uint8_t> foot_skating_flags(const JointsView& clip, const std::vector<int>& toes,
                                        const FootSkatingOptions& opt = {});
double foot_skating_ratio(const JointsView& clip, const std::vector<int>& toes,
                          const FootSkatingOptions& opt = {});
// Mean over clips; toes from skeleton.role("toes").
double foot_skating_ratio(const std::vector<JointsView>& clips, const Skeleton& skeleton,
                          const FootSkatingOptions& opt = {});

// ---------------------------------------------------------------------------
// 4. 2D / 3D lifting metrics (Sketch2Anim, reference-facts §3 and §5)
// ---------------------------------------------------------------------------

// Image-plane keypoints [frames, joints, 2].
struct Keypoints2D {
  int frames = 0;
  int joints = 0;
  std::vector<double> xy;
  Eigen::Vector2d at(int t, int j) const {
    const double* p = xy.data() + (static_cast<size_t>(t) * joints + j) * 2;
    return {p[0], p[1]};
  }
};
// Projects every stored frame of a motion with the camera.
Keypoints2D project_motion(const OrthoCamera& camera, const JointsView& motion);

// Root-aligned 2D error: for each keyframe, mean over joints of
// ||(P(x_j) - P(x_root)) - (y_j - y_root)||, P = camera projection of the prediction,
// y = 2D target; then mean over keyframes.
double mpjpe_2d(const JointsView& prediction, const Keypoints2D& target, const OrthoCamera& camera,
                const std::vector<int>& keyframes, int root = 0);
// Root-aligned 3D error against the ground-truth motion over the keyframes.
double mpjpe_3d(const JointsView& prediction, const JointsView& ground_truth,
                const std::vector<int>& keyframes, int root = 0);
// Mean ||P(x_tj) - y_tj|| over the controlled (frame, joint) entries (mask channels = 1).
double avg_err_2d(const JointsView& prediction, const Keypoints2D& target, const OrthoCamera& camera,
                  const MaskView& controlled);
// Mean ||x_tj - g_tj|| over the controlled entries.
double avg_err_3d(const JointsView& prediction, const JointsView& ground_truth, const MaskView& controlled);

struct LiftingSample {
  JointsView prediction;
  JointsView ground_truth;
  Keypoints2D target_2d;       // usually project_motion(camera, ground_truth)
  OrthoCamera camera;
  std::vector<int> keyframes;  // keypose frames (MPJPE)
  MaskView controlled;         // [T, J, 1] controlled entries (Avg.Err)
};
struct LiftingMetrics {
  double mpjpe_2d = 0.0, mpjpe_3d = 0.0, avg_err_2d = 0.0, avg_err_3d = 0.0;
  int samples = 0;
};
// Each metric per sample, then the mean over samples.
LiftingMetrics lifting_metrics(const std::vector<LiftingSample>& samples, int root = 0);

// ---------------------------------------------------------------------------
// 5. Tokenizer reconstruction MPJPE
// ---------------------------------------------------------------------------

// reconstruction_mpjpe (data/joints_view.h): the models layer measures with it too.

// ---------------------------------------------------------------------------
// 6. Motion realism (evaluator-free; the prior health check, docs/metrics.md)
// ---------------------------------------------------------------------------

// Mean |acceleration| in m/s^2: per clip, the mean over interior valid frames
// t = 1..length-2 and all joints of ||x[t+1] - 2 x[t] + x[t-1]|| * fps^2; then the
// mean over clips. Clips with fewer than 3 valid frames have no interior frame and
// are skipped; UserError when no clip has one.
double mean_abs_acceleration(const JointsView& clip, double fps);
double mean_abs_acceleration(const std::vector<JointsView>& clips, double fps);

// Bone-length drift in millimetres: per clip and bone (joint j to parents[j]), the
// population standard deviation over valid frames of the bone's length; the mean
// over bones, then over clips. A rigid skeleton gives 0.
double bone_length_std_mm(const JointsView& clip, const Skeleton& skeleton);
double bone_length_std_mm(const std::vector<JointsView>& clips, const Skeleton& skeleton);

struct FloorPenetration {
  double depth = 0.0;           // metres: mean over clips of max(0, -min over valid frames and toes of y)
  double frame_fraction = 0.0;  // valid frames (all clips pooled) with some toe strictly below y = 0
};
// Toes = skeleton.role("toes"); the floor is the plane y = 0 (Y up).
FloorPenetration toe_floor_penetration(const std::vector<JointsView>& clips, const Skeleton& skeleton);

// ---------------------------------------------------------------------------
// 7. Replications
// ---------------------------------------------------------------------------

struct Replicated {
  double mean = 0.0;
  double std = 0.0;   // population standard deviation (divides by N), as np.std in the T2M scripts
  double ci95 = 0.0;  // 1.96 * std / sqrt(N)
  int n = 0;
};
Replicated summarize(const std::vector<double>& values);  // UserError if empty or non-finite

using MetricValues = std::map<std::string, double>;
// Calls run(seed0 + r) for r = 0..n-1 and summarises every named metric. Every run
// must report the same metric names (UserError otherwise).
std::map<std::string, Replicated> replicate(int n, uint64_t seed0,
                                            const std::function<MetricValues(uint64_t seed)>& run);

}  // namespace mc
