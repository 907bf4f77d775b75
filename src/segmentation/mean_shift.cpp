#include "mean_shift_internal.h"

#include <pcl_animseg/kdtree.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/progress.h>
#include <pcl_animseg/union_find.h>

#include <flann/flann.hpp>

#include <Eigen/Eigenvalues>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <functional>
#include <future>
#include <limits>
#include <numeric>
#include <queue>
#include <sstream>
#include <unordered_map>

namespace pcl_animseg {
namespace segmentation {

MeanShiftBackend meanShiftBackendFromString(const std::string& name) {
  if (name == "exact") return MeanShiftBackend::Exact;
  if (name == "gkdtree" || name == "gaussian-kdtree") return MeanShiftBackend::GaussianKdTree;
  throw Error("unknown mean shift backend '" + name + "' (expected exact or gkdtree)");
}
MeanShiftMethod meanShiftMethodFromString(const std::string& name) {
  if (name == "paper") return MeanShiftMethod::Paper;
  if (name == "motion") return MeanShiftMethod::Motion;
  throw Error("unknown segmentation method '" + name + "' (expected paper or motion)");
}
std::string toString(MeanShiftBackend backend) {
  return backend == MeanShiftBackend::Exact ? "exact" : "gkdtree";
}
std::string toString(MeanShiftMethod method) {
  return method == MeanShiftMethod::Paper ? "paper" : "motion";
}

double sequenceScale(const PointCloudSequence& sequence) {
  double sum = 0.0;
  for (std::size_t t = 0; t < sequence.size(); ++t) sum += boundingBoxDiagonal(*sequence.frame(t));
  return sequence.empty() ? 0.0 : sum / sequence.size();
}

void MeanShiftSegmentation::setWeights(double w1, double w2, double w3, double w4) {
  params_.w1 = w1;
  params_.w2 = w2;
  params_.w3 = w3;
  params_.w4 = w4;
}

void MeanShiftSegmentation::validate() const {
  const MeanShiftParams& p = params_;
  if (!sequence_ || sequence_->empty())
    throw Error("mean shift: no input sequence (setInputSequence with at least one frame)");
  if (!(p.bandwidth > 0.0) || !std::isfinite(p.bandwidth))
    throw Error("mean shift: bandwidth must be positive (got " + std::to_string(p.bandwidth) + ")");
  for (double w : {p.w1, p.w2, p.w3, p.w4})
    if (!(w >= 0.0) || !std::isfinite(w))
      throw Error("mean shift: weights w1..w4 must be non-negative numbers");
  if (p.w1 + p.w2 <= 0.0)
    throw Error("mean shift: at least one of w1 (normal) and w2 (position) must be positive");
  if (p.max_iterations < 1) throw Error("mean shift: max iterations must be at least 1");
  if (p.refine_iterations < 0) throw Error("mean shift: exact refinement steps must be >= 0");
  if (!(p.gkdtree.leaf_extent > 0.0f) || !std::isfinite(p.gkdtree.leaf_extent) ||
      p.gkdtree.min_leaf_points < 1)
    throw Error("mean shift: Gaussian kd-tree cell extent must be positive and its least points "
                "per cell >= 1");
  if (!(p.merge_radius > 0.0)) throw Error("mean shift: merge radius must be positive");
  if (p.min_cluster_size < 0 || p.neighbours < 1 || p.patches < 0 || p.target_clusters < 0)
    throw Error("mean shift: cluster size, neighbours, patches and target must be >= 0 (k >= 1)");
  if (!(p.motion_threshold > 0.0)) throw Error("mean shift: motion threshold must be positive");
  if (!(p.crease_cost >= 0.0) || !std::isfinite(p.crease_cost))
    throw Error("mean shift: crease cost must be a number >= 0");
  if (!(p.border_smoothness >= 0.0) || !std::isfinite(p.border_smoothness))
    throw Error("mean shift: border smoothness must be a number >= 0");
  if (!(p.dissolve_ratio >= 0.0) || !std::isfinite(p.dissolve_ratio))
    throw Error("mean shift: dissolve ratio must be a number >= 0");
  if (!(p.joint_weight >= 0.0) || !std::isfinite(p.joint_weight))
    throw Error("mean shift: joint weight must be a number >= 0");
  if (!(p.sliver_fraction >= 0.0 && p.sliver_fraction < 1.0))
    throw Error("mean shift: sliver fraction must be in [0, 1)");
  if (!signatures_.empty()) {
    if (signatures_.size() != sequence_->size())
      throw Error("mean shift: " + std::to_string(signatures_.size()) + " signature matrices for " +
                  std::to_string(sequence_->size()) + " frames");
    for (std::size_t t = 0; t < signatures_.size(); ++t)
      if (static_cast<std::size_t>(signatures_[t].rows()) != sequence_->frame(t)->size() ||
          signatures_[t].cols() != signatures_[0].cols())
        throw Error("mean shift: signatures of frame " + std::to_string(t) +
                    " must have one row per point and the same width as frame 0's");
  }
  if (!keypoints_.empty() && keypoints_.size() != sequence_->size())
    throw Error("mean shift: keypoint lists must be given for every frame");
  for (std::size_t t = 0; t < keypoints_.size(); ++t)
    for (int k : keypoints_[t])
      if (k < 0 || static_cast<std::size_t>(k) >= sequence_->frame(t)->size())
        throw Error("mean shift: keypoint index " + std::to_string(k) + " out of range in frame " +
                    std::to_string(t));
}

namespace detail {

namespace {
/** An unordered pair of cluster ids as one sortable key (smaller id in the high half), for the
 * sorted cross-edge lists of the saddles and of the absorption. */
std::uint64_t pairKey(int a, int b) {
  return static_cast<std::uint64_t>(std::min(a, b)) << 32 |
         static_cast<std::uint64_t>(std::max(a, b));
}
int pairFirst(std::uint64_t key) { return static_cast<int>(key >> 32); }
int pairSecond(std::uint64_t key) { return static_cast<int>(key & 0xffffffffu); }
/** Labels of the whole sequence (frames one after the other) cut into frames at `offsets`. */
std::vector<std::vector<int>> splitByFrame(const std::vector<int>& flat,
                                           const std::vector<std::size_t>& offsets) {
  std::vector<std::vector<int>> labels(offsets.size() - 1);
  for (std::size_t t = 0; t + 1 < offsets.size(); ++t)
    labels[t].assign(flat.begin() + offsets[t], flat.begin() + offsets[t + 1]);
  return labels;
}
}  // namespace

StageTimer::StageTimer(const char* prefix)
    : on_(std::getenv("ANIMSEG_MS_TIMING") != nullptr), prefix_(prefix) {
  restart();
}
void StageTimer::restart() { last_ = std::chrono::steady_clock::now(); }
void StageTimer::lap(const char* stage) {
  const auto now = std::chrono::steady_clock::now();
  if (on_)
    std::fprintf(stderr, "[%s] %-28s %8.3f s\n", prefix_, stage,
                 std::chrono::duration<double>(now - last_).count());
  last_ = now;
}

int largestLabel(const std::vector<std::vector<int>>& labels) {
  int largest = -1;
#pragma omp parallel for schedule(static) reduction(max : largest)
  for (int t = 0; t < static_cast<int>(labels.size()); ++t)
    for (int l : labels[t]) largest = std::max(largest, l);
  return largest;
}

JointSpace buildJointSpace(const PointCloudSequence& seq, const std::vector<Eigen::MatrixXf>& sig,
                           const std::vector<std::vector<int>>& keypoints,
                           const MeanShiftParams& params) {
  JointSpace js;
  js.offsets = seq.offsets();
  const std::size_t n = seq.totalPoints();
  const int sd = sig.empty() ? 0 : static_cast<int>(sig[0].cols());
  const int dim = 6 + sd;
  js.scale = sequenceScale(seq);
  // All points identical: any positive scale gives the same (single-cluster) answer.
  const double s = js.scale > 0.0 ? js.scale : 1.0;
  js.z.resize(static_cast<Eigen::Index>(n), dim);
  js.keypoint.assign(n, 0);
  // Frames in parallel: each writes its own rows.
#pragma omp parallel for schedule(dynamic, 1)
  for (std::size_t t = 0; t < seq.size(); ++t) {
    const auto& cloud = *seq.frame(t);
    for (std::size_t j = 0; j < cloud.size(); ++j) {
      const auto& p = cloud[j];
      const Eigen::Index i = static_cast<Eigen::Index>(js.offsets[t] + j);
      js.z(i, 0) = static_cast<float>(p.x / s);
      js.z(i, 1) = static_cast<float>(p.y / s);
      js.z(i, 2) = static_cast<float>(p.z / s);
      Eigen::Vector3f nrm(p.normal_x, p.normal_y, p.normal_z);
      if (!nrm.allFinite() || nrm.norm() < 1e-6f) nrm.setZero();
      else nrm.normalize();
      js.z.block<1, 3>(i, 3) = nrm.transpose();
      if (sd) js.z.block(i, 6, 1, sd) = sig[t].row(static_cast<Eigen::Index>(j));
    }
    if (!keypoints.empty())
      for (int k : keypoints[t]) js.keypoint[js.offsets[t] + k] = 1;
  }
  if (!js.z.allFinite())
    throw Error("mean shift: non-finite positions or signatures in the input");
  js.has_keypoints = sd > 0 && params.w3 != params.w4 &&
                     std::any_of(js.keypoint.begin(), js.keypoint.end(), [](char c) { return c; });
  const double w = params.bandwidth;
  js.metric_plain.resize(dim);
  js.metric_plain.segment(0, 3).setConstant(static_cast<float>(std::sqrt(params.w2) / w));
  js.metric_plain.segment(3, 3).setConstant(static_cast<float>(std::sqrt(params.w1) / w));
  js.metric_key = js.metric_plain;
  if (sd) {
    js.metric_plain.segment(6, sd).setConstant(static_cast<float>(std::sqrt(params.w4) / w));
    js.metric_key.segment(6, sd).setConstant(static_cast<float>(std::sqrt(params.w3) / w));
  }
  return js;
}

// ---- kernel sums ---------------------------------------------------------------------------

struct JointKernelSum::Backend {
  virtual ~Backend() = default;
  /** out.row(r) (+)= sum_j exp(-|q_r - x_j|^2/2) values_j for r in rows. */
  virtual void evaluate(const Eigen::MatrixXf& q, const std::vector<int>& rows,
                        Eigen::MatrixXf& out) const = 0;
  virtual const filters::GaussianKdTree* tree() const { return nullptr; }
  /** Releases what the backend keeps for these query rows (the exact backend's lists). */
  virtual void forget(const std::vector<int>& /*rows*/) const {}
  /** Tree searches made so far (exact backend; diagnostics). */
  virtual long searches() const { return 0; }
};

namespace {

// Kernels of the refinement's chunked exact sums (ExactBackend::evaluateCached), written by hand
// on raw arrays so that GCC can compile them a second time for AVX2 and pick one when the library
// is loaded (the build itself targets plain x86-64). Neither version contracts a multiply and
// an add (no FMA), and each lane does the same operations in the same order, so both give the
// same bits.
#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__) && \
    !defined(__SANITIZE_ADDRESS__)
#define ANIMSEG_AVX2_CLONE __attribute__((target_clones("avx2", "default")))
#else
#define ANIMSEG_AVX2_CLONE
#endif

constexpr std::uint32_t kScanStrip = 32;  // distances computed side by side
constexpr int kValueBlock = 16;           // components of a sum kept in registers together
typedef float Float8 __attribute__((vector_size(32)));
typedef float Float4 __attribute__((vector_size(16)));
typedef double Double4 __attribute__((vector_size(32)));

/** Terms of the points lo..hi-1 within squared distance r2 of q, in index order: their indices
 * and exp(-d2/2). xc holds the data column-major (coordinate k of point i at xc[k * n + i]). Each
 * distance is summed over the coordinates in order, as one point at a time would. */
ANIMSEG_AVX2_CLONE
std::size_t scanTerms(const float* q, const float* xc, std::size_t n, int d, std::uint32_t lo,
                      std::uint32_t hi, float r2, std::uint32_t* index, double* weight) {
  std::size_t terms = 0;
  for (std::uint32_t i0 = lo; i0 < hi; i0 += kScanStrip) {
    const std::uint32_t w = std::min<std::uint32_t>(kScanStrip, hi - i0);
    float t[kScanStrip] = {};
    if (w == kScanStrip) {
      Float8 acc[kScanStrip / 8] = {};
      for (int k = 0; k < d; ++k) {
        const float* xk = xc + static_cast<std::size_t>(k) * n + i0;
        for (std::uint32_t b = 0; b < kScanStrip / 8; ++b) {
          Float8 a;
          std::memcpy(&a, xk + 8 * b, sizeof a);
          a = q[k] - a;
          acc[b] += a * a;
        }
      }
      std::memcpy(t, acc, sizeof acc);
    } else {
      for (int k = 0; k < d; ++k) {
        const float* xk = xc + static_cast<std::size_t>(k) * n + i0;
        for (std::uint32_t i = 0; i < w; ++i) t[i] += (q[k] - xk[i]) * (q[k] - xk[i]);
      }
    }
    for (std::uint32_t i = 0; i < w; ++i)
      if (t[i] < r2) {
        index[terms] = i0 + i;
        weight[terms++] = std::exp(-0.5 * t[i]);
      }
  }
  return terms;
}

/** Terms of the listed points first..last-1 (indices into x, row-major with d coordinates a
 * point) within squared distance r2 of q, in list order: their indices and exp(-d2/2). Eight
 * points side by side, each distance summed over the coordinates in order, as one point at a
 * time would; the rows of the points a few entries ahead are prefetched (the lists are scattered
 * over the data, and waiting for memory was most of this loop's time). */
ANIMSEG_AVX2_CLONE
std::size_t listTerms(const float* q, const float* x, int d, const std::uint32_t* first,
                      const std::uint32_t* last, float r2, std::uint32_t* index, double* weight) {
  constexpr std::ptrdiff_t kAhead = 16;  // entries prefetched ahead
  const std::size_t row = static_cast<std::size_t>(d);
  const std::ptrdiff_t count = last - first;
  std::size_t terms = 0;
  for (std::ptrdiff_t m0 = 0; m0 < count; m0 += 8) {
    const int w = static_cast<int>(std::min<std::ptrdiff_t>(8, count - m0));
    for (std::ptrdiff_t a = m0 + kAhead; a < std::min(count, m0 + kAhead + 8); ++a) {
      const char* xa = reinterpret_cast<const char*>(x + first[a] * row);
      __builtin_prefetch(xa);
      __builtin_prefetch(xa + 64);
    }
    const float* xj[8];
    for (int j = 0; j < 8; ++j) xj[j] = x + first[m0 + std::min(j, w - 1)] * row;
    Float8 acc = {};
    for (int k = 0; k < d; ++k) {
      const Float8 a = {xj[0][k], xj[1][k], xj[2][k], xj[3][k],
                        xj[4][k], xj[5][k], xj[6][k], xj[7][k]};
      const Float8 e = q[k] - a;
      acc += e * e;
    }
    float t[8];
    std::memcpy(t, &acc, sizeof t);
    for (int j = 0; j < w; ++j)
      if (t[j] < r2) {
        index[terms] = first[m0 + j];
        weight[terms++] = std::exp(-0.5 * t[j]);
      }
  }
  return terms;
}

/** acc[c] += weight[e] * values[index[e] * stride + c] for the terms e in order, c < stride (a
 * multiple of kValueBlock): kValueBlock components at a time, kept in registers over the terms. */
ANIMSEG_AVX2_CLONE
void addTerms(const float* values, int stride, const std::uint32_t* index, const double* weight,
              std::size_t terms, double* acc) {
  for (int c0 = 0; c0 < stride; c0 += kValueBlock) {
    Double4 a[kValueBlock / 4];
    std::memcpy(a, acc + c0, sizeof a);
    for (std::size_t e = 0; e < terms; ++e) {
      if (c0 == 0 && e + 8 < terms) {  // the terms' rows are scattered: fetch ahead
        const char* va =
            reinterpret_cast<const char*>(values + static_cast<std::size_t>(index[e + 8]) * stride);
        for (int b = 0; b < stride * 4; b += 64) __builtin_prefetch(va + b);
      }
      const double w = weight[e];
      const float* ve = values + static_cast<std::size_t>(index[e]) * stride + c0;
      for (int b = 0; b < kValueBlock / 4; ++b) {
        Float4 f;
        std::memcpy(&f, ve + 4 * b, sizeof f);
        a[b] += w * __builtin_convertvector(f, Double4);
      }
    }
    std::memcpy(acc + c0, a, sizeof a);
  }
}

// Exact reference: FLANN kd-tree (single tree, exact search) radius search at 3 bandwidths
// (the Gaussian is 1.1% there), then the exact kernel.
class ExactBackend : public JointKernelSum::Backend {
 public:
  /** cache_margin > 0 (the refinement's few, long-lived queries): a query row keeps the list of
   * the data within 3 + margin of where it was last searched (its anchor) and, while it stays
   * within `margin` of the anchor, sums over that list instead of searching the tree again
   * (every point within 3 of the query is on it, so the sums are the same; in sparse 30-D data
   * the tree search is most of an exact step's cost). The cached backend searches the data in
   * their principal axes (a rotation: the same distances up to rounding), where the tree's
   * axis-aligned cuts follow the data; on data so dense that the lists would hold more than a
   * quarter of the points (denseData) it builds no tree and every query scans all points. */
  ExactBackend(const Eigen::MatrixXf& x, const Eigen::MatrixXf& values, float cache_margin = 0.0f)
      : values_count_(values.cols()), margin_(cache_margin) {
    if (margin_ <= 0.0f) {
      values_ = values.transpose();
      x_ = x;
    } else {
      const Eigen::Index vp = (values.cols() + kValueBlock - 1) / kValueBlock * kValueBlock;
      padded_ = Eigen::MatrixXf::Zero(vp, values.rows());
      padded_.topRows(values.cols()) = values.transpose();
      if (denseData(x)) {
        scan_all_ = true;  // no tree: every query scans every point
        xc_ = x;
        return;
      }
      if (x.rows() > 1) {
        const Eigen::RowVectorXd mean = x.cast<double>().colwise().mean();
        Eigen::MatrixXd cov = Eigen::MatrixXd::Zero(x.cols(), x.cols());
        for (Eigen::Index i0 = 0; i0 < x.rows(); i0 += 65536) {
          const Eigen::Index m = std::min<Eigen::Index>(65536, x.rows() - i0);
          const Eigen::MatrixXd c = x.middleRows(i0, m).cast<double>().rowwise() - mean;
          cov.noalias() += c.transpose() * c;
        }
        Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(cov);
        rotation_ = eig.eigenvectors().rowwise().reverse().cast<float>();  // largest axis first
        x_ = x * rotation_;
      } else {
        x_ = x;
      }
      xc_ = x_;  // column-major: a coordinate of consecutive points is contiguous
    }
    index_ = std::make_unique<flann::KDTreeSingleIndex<flann::L2<float>>>(
        flann::Matrix<float>(x_.data(), x_.rows(), x_.cols()),
        flann::KDTreeSingleIndexParams(15));
    index_->buildIndex();
  }
  void evaluate(const Eigen::MatrixXf& q, const std::vector<int>& rows,
                Eigen::MatrixXf& out) const override {
    if (margin_ > 0.0f) {
      evaluateCached(q, rows, out);
      return;
    }
    const int v = static_cast<int>(values_count_);
    const int nr = static_cast<int>(rows.size());
    const int d = static_cast<int>(q.cols());
    const float r2 = 9.0f;
    long searches = 0;
#pragma omp parallel reduction(+ : searches)
    {
      FlannRadiusSearch search;
      std::vector<float> qb(d);
      Eigen::VectorXd acc(v);
#pragma omp for schedule(dynamic, 16)
      for (int r = 0; r < nr; ++r) {
        for (int k = 0; k < d; ++k) qb[k] = q(rows[r], k);
        acc.setZero();
        search(*index_, qb.data(), r2);
        ++searches;
        for (std::size_t m = 0; m < search.indices.size(); ++m)
          acc += std::exp(-0.5 * search.sqr_distances[m]) *
                 values_.col(search.indices[m]).cast<double>();
        for (int c = 0; c < v; ++c) out(rows[r], c) += static_cast<float>(acc[c]);
      }
    }
    searches_ += searches;
  }
  void forget(const std::vector<int>& rows) const override {
    for (int r : rows)
      if (static_cast<std::size_t>(r) < cache_.size()) cache_[r] = Cached();
  }
  long searches() const override { return searches_; }

 private:
  struct Cached {
    std::vector<float> anchor, last;
    std::vector<std::uint32_t> list;  // sorted
    bool scan = false;                // the list held more than a quarter of the data
  };

  /** The cached evaluation (the refinement's few, long-lived queries), in two parallel phases.
   * 1. Each query row renews its neighbour list where it left its anchor. A row whose list
   *    holds more than a quarter of the data (at the paper's bandwidth about half of it lies
   *    within 3.5 bandwidths) drops the list and the searches for good: it scans every point.
   * 2. The data in chunks of kSumChunk consecutive points: a chunk's task sums, for every row,
   *    the terms of the chunk's points that are on the row's list (all of them for a scanning
   *    row), so the chunk is read from memory once per step for all rows. Where most of a chunk
   *    is on the list, the distances of all its points are computed side by side. Each row then
   *    adds its chunks' sums in chunk order: the same sums for any number of threads, and the
   *    rows keep every core busy however few they are. */
  void evaluateCached(const Eigen::MatrixXf& q, const std::vector<int>& rows,
                      Eigen::MatrixXf& out) const {
    const int v = static_cast<int>(values_count_);
    const int nr = static_cast<int>(rows.size());
    const int d = static_cast<int>(q.cols());
    const std::size_t n = static_cast<std::size_t>(xc_.rows());
    const float r2 = 9.0f;
    if (cache_.size() < static_cast<std::size_t>(q.rows())) cache_.resize(q.rows());
    const float wide = (3.0f + margin_) * (3.0f + margin_);
    const float m2 = margin_ * margin_;
    Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> qr(nr, d);
    long searches = 0;
#pragma omp parallel reduction(+ : searches)
    {
      FlannRadiusSearch search;
#pragma omp for schedule(dynamic, 1)
      for (int r = 0; r < nr; ++r) {
        float* qb = qr.data() + static_cast<std::size_t>(r) * d;
        if (rotation_.size()) {
          Eigen::Map<Eigen::RowVectorXf>(qb, d).noalias() = q.row(rows[r]) * rotation_;
        } else {
          for (int k = 0; k < d; ++k) qb[k] = q(rows[r], k);
        }
        Cached& c = cache_[rows[r]];
        c.scan = c.scan || scan_all_;
        if (c.scan) continue;
        float moved = 0.0f;
        if (c.anchor.size() == static_cast<std::size_t>(d))
          for (int k = 0; k < d; ++k) moved += (qb[k] - c.anchor[k]) * (qb[k] - c.anchor[k]);
        if (c.anchor.size() == static_cast<std::size_t>(d) && moved <= m2) continue;
        // Anchored ahead of the query along its last move (trajectories keep their direction),
        // so that the list lasts about twice as long; the query itself is within the margin of
        // the anchor, so the list holds everything within 3 of it.
        std::vector<float> anchor(qb, qb + d);
        if (c.last.size() == static_cast<std::size_t>(d)) {
          float len2 = 0.0f;
          for (int k = 0; k < d; ++k) len2 += (qb[k] - c.last[k]) * (qb[k] - c.last[k]);
          if (len2 > 0.0f) {
            const float t = lead_ * margin_ / std::sqrt(len2);
            for (int k = 0; k < d; ++k) anchor[k] += t * (qb[k] - c.last[k]);
          }
        }
        search(*index_, anchor.data(), wide);
        ++searches;
        c.anchor = anchor;
        if (search.indices.size() * 4 > n) {
          c.scan = true;
          std::vector<std::uint32_t>().swap(c.list);
          continue;
        }
        c.list.assign(search.indices.begin(), search.indices.end());
        std::sort(c.list.begin(), c.list.end());
      }
    }
    searches_ += searches;
    const int vp = static_cast<int>(padded_.rows());
    // Rows that scan or have long lists go by chunks (below); the others sum their own lists,
    // one row per task.
    std::vector<int> wide_rows, narrow_rows;
    for (int r = 0; r < nr; ++r) {
      const Cached& c = cache_[rows[r]];
      (c.scan || c.list.size() > kLongList ? wide_rows : narrow_rows).push_back(r);
    }
#pragma omp parallel
    {
      std::vector<std::uint32_t> term_index;
      std::vector<double> term_weight, acc(vp);
#pragma omp for schedule(dynamic, 16)
      for (std::size_t i = 0; i < narrow_rows.size(); ++i) {
        const int r = narrow_rows[i];
        const std::vector<std::uint32_t>& list = cache_[rows[r]].list;
        term_index.resize(list.size());
        term_weight.resize(list.size());
        const std::size_t terms =
            listTerms(qr.data() + static_cast<std::size_t>(r) * d, x_.data(), d, list.data(),
                      list.data() + list.size(), r2, term_index.data(), term_weight.data());
        std::fill(acc.begin(), acc.end(), 0.0);
        addTerms(padded_.data(), vp, term_index.data(), term_weight.data(), terms, acc.data());
        for (int k = 0; k < v; ++k) out(rows[r], k) += static_cast<float>(acc[k]);
      }
    }
    // The wide rows in batches whose partial sums take at most kPartialBytes (each row's sums
    // do not depend on the batch).
    const std::size_t nc = (n + kSumChunk - 1) / kSumChunk;
    const std::size_t batch =
        std::max<std::size_t>(1, kPartialBytes / (sizeof(double) * vp * nc));
    Eigen::MatrixXd partial;
    for (std::size_t w0 = 0; w0 < wide_rows.size(); w0 += batch) {
      const std::size_t nw = std::min(batch, wide_rows.size() - w0);
      const int* wide = wide_rows.data() + w0;
      partial.setZero(vp, static_cast<Eigen::Index>(nc * nw));
#pragma omp parallel
      {
        std::vector<std::uint32_t> term_index(kSumChunk);  // the terms within 3, in index order
        std::vector<double> term_weight(kSumChunk);
#pragma omp for schedule(dynamic, 1)
        for (std::ptrdiff_t ch = 0; ch < static_cast<std::ptrdiff_t>(nc); ++ch) {
          const std::uint32_t lo = static_cast<std::uint32_t>(ch * kSumChunk);
          const std::uint32_t hi = static_cast<std::uint32_t>(std::min(n, (ch + 1) * kSumChunk));
          for (std::size_t w = 0; w < nw; ++w) {
            const Cached& c = cache_[rows[wide[w]]];
            const std::uint32_t* from = c.list.data();
            const std::uint32_t* to = from;
            if (!c.scan) {
              from = std::lower_bound(c.list.data(), c.list.data() + c.list.size(), lo);
              to = std::lower_bound(from, c.list.data() + c.list.size(), hi);
              if (from == to) continue;
            }
            const float* qb = qr.data() + static_cast<std::size_t>(wide[w]) * d;
            // All the chunk's points where most of them are on the list: the list holds every
            // point within 3 of the query, so the points within 3 are the same terms in the
            // same order as the list's.
            const std::size_t terms = c.scan || static_cast<std::size_t>(to - from) * 4 >= hi - lo
                                          ? scanTerms(qb, xc_.data(), n, d, lo, hi, r2,
                                                      term_index.data(), term_weight.data())
                                          : listTerms(qb, x_.data(), d, from, to, r2,
                                                      term_index.data(), term_weight.data());
            addTerms(padded_.data(), vp, term_index.data(), term_weight.data(), terms,
                     partial.data() + (w * nc + ch) * vp);
          }
        }
      }
      for (std::size_t w = 0; w < nw; ++w) {
        const double* first = partial.data() + w * nc * vp;
        for (int k = 0; k < v; ++k) {
          double sum = 0.0;
          for (std::size_t ch = 0; ch < nc; ++ch) sum += first[ch * vp + k];
          out(rows[wide[w]], k) += static_cast<float>(sum);
        }
      }
    }
    for (int r = 0; r < nr; ++r) {
      const float* qb = qr.data() + static_cast<std::size_t>(r) * d;
      cache_[rows[r]].last.assign(qb, qb + d);
    }
  }

  /** Whether the data are so dense at the bandwidth that a query's neighbour list would hold
   * more than a quarter of them (then every query scans all points, and no tree is built): the
   * median over 32 of the data points, each counting its neighbours within 3 + margin among
   * about 2^16 evenly spaced points. Only a question of speed: scans and lists give the same
   * sums. */
  bool denseData(const Eigen::MatrixXf& x) const {
    const Eigen::Index n = x.rows();
    if (n < 4096) return false;
    const Eigen::Index step = std::max<Eigen::Index>(1, n / 65536);
    const Eigen::Index m = (n + step - 1) / step;
    Eigen::MatrixXf sample(m, x.cols());
    for (Eigen::Index i = 0; i < m; ++i) sample.row(i) = x.row(i * step);
    const float wide = (3.0f + margin_) * (3.0f + margin_);
    std::vector<double> share(32);
#pragma omp parallel for schedule(dynamic, 1)
    for (int s = 0; s < 32; ++s) {
      const Eigen::RowVectorXf q = x.row(s * (n / 32));
      share[s] = static_cast<double>(((sample.rowwise() - q).rowwise().squaredNorm().array() <
                                      wide).count()) / static_cast<double>(m);
    }
    std::nth_element(share.begin(), share.begin() + 16, share.end());
    return share[16] > 0.25;
  }

  static constexpr std::size_t kSumChunk = 2048;  // data points per parallel partial sum
  static constexpr std::size_t kLongList = 4 * kSumChunk;  // longer lists are summed by chunks
  static constexpr std::size_t kPartialBytes = std::size_t{64} << 20;  // chunk sums of a batch
  Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> x_;
  Eigen::MatrixXf xc_;      // x_ column-major (cached backend only)
  Eigen::MatrixXf padded_;  // values_ with zero rows up to a multiple of kValueBlock (cached)
  Eigen::MatrixXf values_;  // v x n (uncached backend only)
  Eigen::Index values_count_ = 0;  // v
  std::unique_ptr<flann::KDTreeSingleIndex<flann::L2<float>>> index_;
  float margin_ = 0.0f;
  float lead_ = 0.8f;  // anchor this many margins ahead of the query (see evaluateCached)
  Eigen::MatrixXf rotation_;  // d x d principal axes (columns), empty: none
  bool scan_all_ = false;  // dense data (denseData): no tree, every query scans every point
  mutable std::vector<Cached> cache_;
  mutable long searches_ = 0;
};

class GkdBackend : public JointKernelSum::Backend {
 public:
  GkdBackend(const Eigen::MatrixXf& x, const Eigen::MatrixXf& values,
             const filters::GaussianKdTreeParams& params)
      : tree_(params) {
    StageTimer timer;
    tree_.build(x);
    timer.lap("gkdtree build");
    if (timer.on())
      std::fprintf(stderr, "[mean shift] gkdtree: %ld points, %zu samples (N/M %.1f)\n",
                   static_cast<long>(x.rows()), tree_.numSamples(), tree_.samplingFactor());
    tree_.splatBlur(values, sample_values_);
    timer.lap("gkdtree splat + blur");
  }
  void evaluate(const Eigen::MatrixXf& q, const std::vector<int>& rows,
                Eigen::MatrixXf& out) const override {
    Eigen::MatrixXf tmp(out.rows(), out.cols());
    tree_.slice(sample_values_, q, rows, tmp);
    for (int r : rows) out.row(r) += tmp.row(r);
  }
  const filters::GaussianKdTree* tree() const override { return &tree_; }

 private:
  filters::GaussianKdTree tree_;
  Eigen::MatrixXf sample_values_;
};

}  // namespace

struct JointKernelSum::Group {
  std::unique_ptr<Backend> backend;
  bool key_metric = false;  // data and queries scaled by metric_key
  int applies_to = 0;       // 0: every query, 1: plain queries only, 2: keypoint queries only
};

JointKernelSum::JointKernelSum(const JointSpace& space, const Eigen::MatrixXf& values,
                               const MeanShiftParams& params, float exact_cache_margin,
                               Eigen::Index plain_stride)
    : space_(space), value_count_(static_cast<int>(values.cols())) {
  auto make = [&](std::vector<Eigen::Index> idx, bool key, int applies) {
    if (idx.empty()) return;
    // Every stride-th point stands for the points around it in the list (weight: how many).
    float weight = 1.0f;
    if (!key && applies == 0 && plain_stride > 1) {
      const std::size_t all = idx.size();
      std::vector<Eigen::Index> kept;
      for (std::size_t i = 0; i < all; i += static_cast<std::size_t>(plain_stride))
        kept.push_back(idx[i]);
      weight = static_cast<float>(all) / static_cast<float>(kept.size());
      idx.swap(kept);
    }
    const Eigen::RowVectorXf& m = key ? space.metric_key : space.metric_plain;
    Eigen::MatrixXf x(idx.size(), space.z.cols());
    Eigen::MatrixXf v(idx.size(), values.cols());
    for (std::size_t i = 0; i < idx.size(); ++i) {
      x.row(i) = space.z.row(idx[i]).cwiseProduct(m);
      v.row(i) = weight * values.row(idx[i]);
    }
    auto g = std::make_unique<Group>();
    g->key_metric = key;
    g->applies_to = applies;
    if (params.backend == MeanShiftBackend::Exact)
      g->backend = std::make_unique<ExactBackend>(x, v, exact_cache_margin);
    else
      g->backend = std::make_unique<GkdBackend>(x, v, params.gkdtree);
    groups_.push_back(std::move(g));
  };
  std::vector<Eigen::Index> plain, key;
  const std::vector<char> none;
  splitByKeypoint(space.has_keypoints ? space.keypoint : none, space.z.rows(), plain, key);
  make(plain, false, 0);
  make(key, false, 1);  // Eq. 6 between a keypoint and a non-keypoint query
  make(key, true, 2);   // Eq. 5 between two keypoints
}

JointKernelSum::~JointKernelSum() = default;

void JointKernelSum::forget(const std::vector<int>& rows) const {
  for (const auto& g : groups_) g->backend->forget(rows);
}

long JointKernelSum::searches() const {
  long s = 0;
  for (const auto& g : groups_) s += g->backend->searches();
  return s;
}

double JointKernelSum::samplingFactor() const {
  for (const auto& g : groups_)
    if (g->applies_to == 0)  // the tree over the non-keypoint points: (nearly) all of them
      if (const filters::GaussianKdTree* t = g->backend->tree()) return t->samplingFactor();
  return 0.0;
}

const filters::GaussianKdTree* JointKernelSum::cellTree() const {
  if (groups_.size() != 1 || groups_[0]->key_metric) return nullptr;
  return groups_[0]->backend->tree();
}

void JointKernelSum::evaluate(const Eigen::MatrixXf& y, const std::vector<int>& rows,
                              const std::vector<char>& query_key, Eigen::MatrixXf& out) const {
  for (int r : rows) out.row(r).setZero();
  std::vector<int> plain_rows, key_rows;
  for (int r : rows) (!query_key.empty() && query_key[r] ? key_rows : plain_rows).push_back(r);
  Eigen::MatrixXf q;
  for (const auto& g : groups_) {
    const std::vector<int>& rr =
        g->applies_to == 0 ? rows : (g->applies_to == 1 ? plain_rows : key_rows);
    if (rr.empty()) continue;
    const Eigen::RowVectorXf& m = g->key_metric ? space_.metric_key : space_.metric_plain;
    q.resize(y.rows(), y.cols());
    // Only the rows asked for are scaled (the others may be stale or huge).
    for (int r : rr) q.row(r) = y.row(r).cwiseProduct(m);
    g->backend->evaluate(q, rr, out);
  }
}

std::vector<int> knnGraph(const PointCloudSequence& seq, int k) {
  const auto offsets = seq.offsets();
  std::vector<int> graph(seq.totalPoints() * k, -1);
  // A frame a task (its tree built and searched by one thread): the trees' builds are serial,
  // and a frame's searches are too few to share among many threads.
#pragma omp parallel
  {
    std::vector<int> idx;
    std::vector<float> d2;
#pragma omp for schedule(dynamic, 1)
    for (std::size_t t = 0; t < seq.size(); ++t) {
      const auto& cloud = seq.frame(t);
      if (cloud->size() < 2) continue;
      pcl_animseg::KdTree<pcl::PointNormal> tree;
      tree.setInputCloud(cloud);
      const int kk = std::min<int>(k + 1, static_cast<int>(cloud->size()));
      const int n = static_cast<int>(cloud->size());
      for (int j = 0; j < n; ++j) {
        tree.nearestKSearch((*cloud)[j], kk, idx, d2);
        int c = 0;
        for (int m : idx) {
          if (m == j || c >= k) continue;
          graph[(offsets[t] + j) * k + c++] = static_cast<int>(offsets[t] + m);
        }
      }
    }
  }
  return graph;
}

namespace {
using DensityFn =
    std::function<void(const Eigen::MatrixXf&, const std::vector<char>&, Eigen::MatrixXf&)>;
void finishWith(const JointSpace& space, const std::vector<int>& flat, int num_clusters,
                const std::vector<int>& graph, int k, bool modes_known, const DensityFn& dens,
                const Eigen::MatrixXf& f, SegmentationResult& result);
}  // namespace

namespace {
/** finishResult with the iteration's sums: evaluate(q, rows, query_key, out), v value columns
 * (the last: the density). */
template <typename Sums>
void finishWithSums(const JointSpace& space, const std::vector<int>& flat, int num_clusters,
                    const std::vector<int>& graph, int k, Sums& sums, int v,
                    const Eigen::VectorXf& point_density, SegmentationResult& result) {
  DensityFn dens = [&](const Eigen::MatrixXf& q, const std::vector<char>& qk, Eigen::MatrixXf& o) {
    std::vector<int> rows(q.rows());
    std::iota(rows.begin(), rows.end(), 0);
    Eigen::MatrixXf all(q.rows(), v);
    sums.evaluate(q, rows, qk, all);
    o = all.col(v - 1);
  };
  finishWith(space, flat, num_clusters, graph, k, true, dens, point_density, result);
}
}  // namespace

void finishResult(const JointSpace& space, const std::vector<int>& flat, int num_clusters,
                  const std::vector<int>& graph, int k, const JointKernelSum& sums,
                  const Eigen::VectorXf& point_density, SegmentationResult& result) {
  finishWithSums(space, flat, num_clusters, graph, k, sums, sums.valueCount(), point_density,
                 result);
}

void finishResult(const JointSpace& space, const std::vector<int>& flat, int num_clusters,
                  const std::vector<int>& graph, int k, DeviceExactSums& sums,
                  const Eigen::VectorXf& point_density, SegmentationResult& result) {
  finishWithSums(space, flat, num_clusters, graph, k, sums, static_cast<int>(space.z.cols()) + 1,
                 point_density, result);
}

void finishResult(const JointSpace& space, const std::vector<int>& flat, int num_clusters,
                  const std::vector<int>& graph, int k, const MeanShiftParams& params,
                  bool modes_known, SegmentationResult& result, MeanShiftDeviceBackend* device) {
  const Eigen::Index n = space.z.rows();
  // Density (Eq. 4) at the points and, when known, at the modes: on the device or the CPU.
  DensityFn dens;
  std::unique_ptr<JointKernelSum> cpu;
  const std::vector<char> no_keys;
  if (device) {
    const std::vector<char>& keys = space.has_keypoints ? space.keypoint : no_keys;
    dens = [&, device](const Eigen::MatrixXf& q, const std::vector<char>& qk, Eigen::MatrixXf& o) {
      Eigen::VectorXf v;
      device->density(space.z, space.metric_plain, space.metric_key, keys, params, q,
                      space.has_keypoints ? qk : no_keys, v);
      o = v;
    };
  } else {
    // Without known modes (the motion method) the densities only name each cluster's densest
    // point and its saddles, for the record (its hierarchy follows its own merges): on large
    // inputs the sums run over every stride-th non-keypoint point, weighted to stand for the
    // others (a Monte Carlo estimate of Eq. 4 over at least kDensityPoints points), keypoints
    // exact. 796k points: stride 3, the step 9.1 s -> 3.5 s together with the sparse queries
    // below; mode and saddle densities within 7% of the full sums.
    constexpr Eigen::Index kDensityPoints = 200000;
    const Eigen::Index stride = modes_known ? 1 : std::max<Eigen::Index>(1, n / kDensityPoints);
    cpu = std::make_unique<JointKernelSum>(space, Eigen::MatrixXf::Ones(n, 1), params, 0.0f,
                                           stride);
    dens = [&](const Eigen::MatrixXf& q, const std::vector<char>& qk, Eigen::MatrixXf& o) {
      std::vector<int> rows(q.rows());
      std::iota(rows.begin(), rows.end(), 0);
      o.resize(q.rows(), 1);
      cpu->evaluate(q, rows, qk, o);
    };
  }
  Eigen::MatrixXf f;
  if (modes_known) {
    dens(space.z, space.keypoint, f);
  } else {
    // Modes are the densest points of their clusters and saddles come from the k-NN edges
    // across clusters: the density is needed at both ends of every such edge and, for the modes,
    // near each cluster's densest point, not at every point. Queried: the cross-edge ends, every
    // kModeStride-th point (and each cluster's first), then, a few rounds, the unqueried k-NN
    // neighbours of each cluster's densest point so far (a hill climb). A mode stays at least as
    // dense as its saddles (both ends of a saddle's edge are queried).
    constexpr Eigen::Index kModeStride = 8;
    constexpr int kModeRounds = 4;
    f = Eigen::MatrixXf::Constant(n, 1, std::numeric_limits<float>::quiet_NaN());
    auto query = [&](const std::vector<int>& rows) {
      if (rows.empty()) return;
      Eigen::MatrixXf q(rows.size(), space.z.cols());
      std::vector<char> qk;
      for (std::size_t r = 0; r < rows.size(); ++r) q.row(r) = space.z.row(rows[r]);
      if (!space.keypoint.empty())
        for (int i : rows) qk.push_back(space.keypoint[i]);
      Eigen::MatrixXf fq;
      dens(q, qk, fq);
      for (std::size_t r = 0; r < rows.size(); ++r) f(rows[r], 0) = fq(r, 0);
    };
    std::vector<char> need(static_cast<std::size_t>(n), 0);
    std::vector<char> seen(static_cast<std::size_t>(std::max(num_clusters, 0)), 0);
    for (Eigen::Index i = 0; i < n; ++i) {
      const int a = flat[i];
      if (a < 0) continue;
      if (i % kModeStride == 0 || !seen[a]) need[i] = 1, seen[a] = 1;
      for (int m = 0; m < k; ++m) {
        const int j = graph[i * k + m];
        if (j < 0 || flat[j] < 0 || flat[j] == a) continue;
        need[i] = 1;
        need[j] = 1;
      }
    }
    std::vector<int> rows;
    for (Eigen::Index i = 0; i < n; ++i)
      if (need[i]) rows.push_back(static_cast<int>(i));
    // Each cluster's densest queried point (the first of equals), kept up to date with each
    // batch of queries.
    std::vector<int> top(static_cast<std::size_t>(std::max(num_clusters, 0)), -1);
    auto queryAndClimb = [&](const std::vector<int>& batch) {
      query(batch);
      for (int i : batch) {
        const int a = flat[i];
        if (a < 0 || std::isnan(f(i, 0))) continue;
        const int t = top[a];
        if (t < 0 || f(i, 0) > f(t, 0) || (f(i, 0) == f(t, 0) && i < t)) top[a] = i;
      }
    };
    queryAndClimb(rows);
    for (int round = 0; round < kModeRounds; ++round) {
      rows.clear();
      for (int i : top) {
        if (i < 0) continue;
        for (int m = 0; m < k; ++m) {
          const int j = graph[static_cast<Eigen::Index>(i) * k + m];
          if (j >= 0 && flat[j] == flat[i] && !need[j]) need[j] = 1, rows.push_back(j);
        }
      }
      if (rows.empty()) break;
      queryAndClimb(rows);
    }
  }
  finishWith(space, flat, num_clusters, graph, k, modes_known, dens, f, result);
}

namespace {
void finishWith(const JointSpace& space, const std::vector<int>& flat, int num_clusters,
                const std::vector<int>& graph, int k, bool modes_known, const DensityFn& dens,
                const Eigen::MatrixXf& f, SegmentationResult& result) {
  const Eigen::Index n = space.z.rows();
  result.num_clusters = num_clusters;
  if (!modes_known) {
    result.modes.resize(num_clusters, space.z.cols());
    result.mode_density.assign(num_clusters, -1.0);
    for (Eigen::Index i = 0; i < n; ++i) {
      const int c = flat[i];
      if (c < 0 || std::isnan(f(i, 0))) continue;  // not evaluated (see finishResult)
      if (f(i, 0) > result.mode_density[c]) {
        result.mode_density[c] = f(i, 0);
        result.modes.row(c) = space.z.row(i);
      }
    }
  } else {
    // Density at the modes themselves (Eq. 4), queried as plain points.
    Eigen::MatrixXf fm;
    dens(result.modes, {}, fm);
    result.mode_density.resize(num_clusters);
    for (int c = 0; c < num_clusters; ++c) result.mode_density[c] = fm(c, 0);
    // The filter is approximate: keep a mode at least as dense as its cluster's points, so that
    // persistence (mode minus saddle, Eq. 12) is never negative.
    for (Eigen::Index i = 0; i < n; ++i)
      if (flat[i] >= 0)
        result.mode_density[flat[i]] = std::max<double>(result.mode_density[flat[i]], f(i, 0));
  }
  // Saddle between adjacent clusters: the highest min(f_i, f_j) over k-NN pairs across them,
  // per pair of clusters (a maximum: the same whatever the order), pairs in increasing (a, b)
  // order. Points in parallel, each thread with its own pairs, merged after.
  std::unordered_map<std::uint64_t, float> best;
#pragma omp parallel
  {
    std::unordered_map<std::uint64_t, float> mine;
#pragma omp for schedule(static) nowait
    for (Eigen::Index i = 0; i < n; ++i) {
      const int a = flat[i];
      if (a < 0) continue;
      for (int m = 0; m < k; ++m) {
        const int j = graph[i * k + m];
        if (j < 0) continue;
        const int b = flat[j];
        if (b < 0 || b == a) continue;
        const float v = std::min(f(i, 0), f(j, 0));
        const auto [it, fresh] = mine.emplace(pairKey(a, b), v);
        if (!fresh) it->second = std::max(it->second, v);
      }
    }
#pragma omp critical(mean_shift_saddles)
    for (const auto& [key, v] : mine) {
      const auto [it, fresh] = best.emplace(key, v);
      if (!fresh) it->second = std::max(it->second, v);
    }
  }
  std::vector<std::pair<std::uint64_t, float>> cross(best.begin(), best.end());
  std::sort(cross.begin(), cross.end());
  result.saddles.clear();
  for (const auto& [key, v] : cross)
    result.saddles.push_back({pairFirst(key), pairSecond(key), static_cast<double>(v)});
  result.labels = splitByFrame(flat, space.offsets);
}
}  // namespace

}  // namespace detail

namespace {

/** The integer cells of the rows of y (n x d): cells[i * width + c] = floor(y(i, c) * metric[c] /
 * cell) for c < d (the float expression the groupings always used), and, when width is d + 1, the
 * row's flag in the last column (row_flag[i], 0 without flags). Rows in parallel, in blocks. */
std::vector<int> cellCoordinates(const Eigen::MatrixXf& y, const Eigen::RowVectorXf& metric,
                                 float cell, const std::vector<char>& row_flag, int width) {
  const Eigen::Index n = y.rows();
  const int d = static_cast<int>(y.cols());
  std::vector<int> cells(static_cast<std::size_t>(n) * width, 0);
  constexpr Eigen::Index kBlock = 1024;
  const Eigen::Index blocks = (n + kBlock - 1) / kBlock;
#pragma omp parallel for schedule(static)
  for (Eigen::Index b = 0; b < blocks; ++b) {
    const Eigen::Index lo = b * kBlock, hi = std::min(n, lo + kBlock);
    for (int c = 0; c < d; ++c) {
      const float m = metric[c];
      const float* col = y.data() + static_cast<std::size_t>(c) * n;
      for (Eigen::Index i = lo; i < hi; ++i)
        cells[static_cast<std::size_t>(i) * width + c] =
            static_cast<int>(std::floor(col[i] * m / cell));
    }
    if (width > d && !row_flag.empty())
      for (Eigen::Index i = lo; i < hi; ++i)
        cells[static_cast<std::size_t>(i) * width + d] = row_flag[i];
  }
  return cells;
}

/** Groups equal rows of `cells` (n rows of `width` ints): group_of[i] is row i's group, groups
 * numbered in the order of their first rows, which are returned. An open-addressing table of
 * the rows' hashes (computed in parallel); the rows are then taken in order, so the numbering
 * is the one a map filled row by row gives. */
std::vector<int> groupEqualRows(const std::vector<int>& cells, int width,
                                std::vector<int>& group_of) {
  const std::size_t n = width > 0 ? cells.size() / static_cast<std::size_t>(width) : 0;
  group_of.assign(n, 0);
  std::vector<int> first;
  if (n == 0) return first;
  std::vector<std::uint64_t> hash(n);
#pragma omp parallel for schedule(static)
  for (std::ptrdiff_t i = 0; i < static_cast<std::ptrdiff_t>(n); ++i) {
    const int* row = cells.data() + static_cast<std::size_t>(i) * width;
    std::uint64_t h = 0x9e3779b97f4a7c15ull;
    for (int c = 0; c < width; ++c) {
      h = (h ^ static_cast<std::uint32_t>(row[c])) * 0xff51afd7ed558ccdull;
      h ^= h >> 31;
    }
    hash[i] = h;
  }
  std::size_t size = 16;
  while (size < 2 * n) size <<= 1;
  const std::size_t mask = size - 1;
  std::vector<int> slot(size, -1);  // the group in the slot
  const std::size_t bytes = sizeof(int) * static_cast<std::size_t>(width);
  for (std::size_t i = 0; i < n; ++i) {
    const int* row = cells.data() + i * width;
    std::size_t at = hash[i] & mask;
    for (;;) {
      const int g = slot[at];
      if (g < 0) {
        slot[at] = static_cast<int>(first.size());
        group_of[i] = static_cast<int>(first.size());
        first.push_back(static_cast<int>(i));
        break;
      }
      const std::size_t f = static_cast<std::size_t>(first[g]);
      if (hash[f] == hash[i] && std::memcmp(cells.data() + f * width, row, bytes) == 0) {
        group_of[i] = g;
        break;
      }
      at = (at + 1) & mask;
    }
  }
  return first;
}

}  // namespace

void groupModes(const Eigen::MatrixXf& y, const Eigen::RowVectorXf& metric_plain,
                const Eigen::VectorXf& density, double merge_radius, std::vector<int>& labels,
                std::vector<int>& mode_rep) {
  const Eigen::Index n = y.rows();
  const int dim = static_cast<int>(y.cols());
  if (density.size() != n || metric_plain.size() != dim)
    throw Error("groupModes: sizes of end points, density and metric differ");
  if (!(merge_radius > 0.0)) throw Error("groupModes: merge radius must be positive");
  labels.assign(n, 0);
  mode_rep.clear();
  if (n == 0) return;
  // 1. End points that coincide (cells of a fifth of the merge radius) form one group,
  //    represented by its densest point (the first of them). Hash of the integer cell
  //    coordinates: O(N d).
  using RowMatrix = Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>;
  const float cell = static_cast<float>(merge_radius / 5.0);
  std::vector<int> group_of;
  std::vector<int> group_rep =
      groupEqualRows(cellCoordinates(y, metric_plain, cell, {}, dim), dim, group_of);
  for (Eigen::Index i = 0; i < n; ++i) {
    int& rep = group_rep[group_of[i]];
    if (density[i] > density[rep]) rep = static_cast<int>(i);
  }
  const int ng = static_cast<int>(group_rep.size());
  std::vector<int> order(ng);
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(), [&](int a, int b) {
    return density[group_rep[a]] > density[group_rep[b]];
  });
  // 2. Greedy from the densest group: a group joins the first (densest) kept mode within the
  //    merge radius, else it becomes a mode. Every kept mode was visited before the group, so
  //    "the densest kept mode among the group's neighbours within r" is the same answer as the
  //    scan over all kept modes, found with one radius search per group in a kd-tree over the
  //    group representatives (O(G log G) for the well-separated groups mean shift leaves, instead
  //    of O(G x modes), which did not finish at 800k points with ~10^4 unconverged groups).
  RowMatrix reps(ng, dim);
  for (int g = 0; g < ng; ++g) reps.row(g) = y.row(group_rep[g]).cwiseProduct(metric_plain);
  std::vector<int> group_mode(ng, -1);
  const float r2 = static_cast<float>(merge_radius * merge_radius);
  if (ng > 1) {
    flann::KDTreeSingleIndex<flann::L2<float>> index(flann::Matrix<float>(reps.data(), ng, dim),
                                                     flann::KDTreeSingleIndexParams(15));
    index.buildIndex();
    // Radius searches in parallel (read-only), then the sequential greedy pass over the lists.
    std::vector<std::vector<int>> near(ng);
#pragma omp parallel
    {
      FlannRadiusSearch search;
#pragma omp for schedule(dynamic, 64)
      for (int g = 0; g < ng; ++g) {
        // FLANN keeps squared distances below the radius; a hair more, then the exact test below
        // (the same float expression as the old all-pairs scan) decides.
        search(index, reps.data() + static_cast<std::size_t>(g) * dim, r2 * 1.001f);
        for (std::size_t jj : search.indices) {
          const int j = static_cast<int>(jj);
          if (j != g && (reps.row(j) - reps.row(g)).squaredNorm() < r2) near[g].push_back(j);
        }
      }
    }
    for (int g : order) {
      int found = -1;
      for (int j : near[g]) {
        const int m = group_mode[j];
        // j is a kept mode (its own representative) visited before g.
        if (m >= 0 && mode_rep[m] == group_rep[j] && (found < 0 || m < found)) found = m;
      }
      if (found < 0) {
        found = static_cast<int>(mode_rep.size());
        mode_rep.push_back(group_rep[g]);
      }
      group_mode[g] = found;
    }
  } else {
    group_mode[0] = 0;
    mode_rep.push_back(group_rep[0]);
  }
  for (Eigen::Index i = 0; i < n; ++i) labels[i] = group_mode[group_of[i]];
}

namespace {

using detail::JointKernelSum;
using detail::JointSpace;
using detail::StageTimer;

/** The values the kernel sums of Eq. 10 carry: each point's z and a 1 (homogeneous coordinates,
 * so that the last column is the denominator of Eq. 8). */
Eigen::MatrixXf homogeneousValues(const JointSpace& space) {
  const int dim = static_cast<int>(space.z.cols());
  Eigen::MatrixXf values(space.z.rows(), dim + 1);
  values.leftCols(dim) = space.z;
  values.col(dim).setOnes();
  return values;
}

/** Hybrid ending of the Gaussian kd-tree backend: the approximate iteration leaves the end points
 * near the modes of the approximated density, whose small ripples (cells replaced by their means,
 * queries interpolated between nearby cells) add modes and stop points on slopes. The end points
 * are grouped in cells of a tenth of the merge radius and each group's first point continues with
 * up to `refine_iterations` EXACT mean shift steps (the exact backend's kernel sums over all data
 * points); the group follows it. Cheap because groups are few compared with points. On sparse
 * data the tree search in 30-D is most of an exact step's cost (the ~50 points within 3
 * bandwidths are quickly summed), so each group keeps its neighbour list while it moves less than
 * half a bandwidth (JointKernelSum's cache margin; the same sums) and the tree is built in the
 * data's principal axes: together 2.5-3x fewer seconds than a plain search per step. On dense
 * data (the paper's bandwidth: half of the data within 3.5 bandwidths of a group) the sums are
 * the cost, and the few groups' steps are summed together chunk by chunk of the data on every
 * core (see ExactBackend::evaluateCached). With `progress`, the first step (every group's, most of
 * the work when the groups start from data points) reports how many groups it has summed. */
void refineEndPoints(const JointSpace& space, const MeanShiftParams& params,
                     const std::vector<char>& row_key, Eigen::MatrixXf& y,
                     Progress* progress = nullptr, DeviceExactSums* device_sums = nullptr) {
  StageTimer timer;
  const Eigen::Index n = y.rows();  // end points: one per data point or per cell
  const int dim = static_cast<int>(y.cols());
  const float cell = static_cast<float>(params.merge_radius / 10.0);
  std::vector<int> group_of;
  const std::vector<int> rep = groupEqualRows(
      cellCoordinates(y, space.metric_plain, cell, row_key, dim + 1), dim + 1, group_of);
  std::string key(sizeof(int) * dim + 1, '\0');
  const int g = static_cast<int>(rep.size());
  Eigen::MatrixXf yg(g, dim);
  std::vector<char> key_of(row_key.empty() ? 0 : g);
  for (int r = 0; r < g; ++r) {
    yg.row(r) = y.row(rep[r]);
    if (!row_key.empty()) key_of[r] = row_key[rep[r]];
  }
  MeanShiftParams exact_params = params;
  exact_params.backend = MeanShiftBackend::Exact;
  // Each group keeps its neighbour list within 3.5 bandwidths while it moves less than 0.5 (the
  // 30-D tree search, not the sum over the ~50 points it finds, is what an exact step costs).
  // On a device the same sums run there instead.
  std::unique_ptr<JointKernelSum> cpu_exact;
  if (!device_sums)
    cpu_exact =
        std::make_unique<JointKernelSum>(space, homogeneousValues(space), exact_params, 0.5f);
  auto evaluate = [&](const std::vector<int>& rows, Eigen::MatrixXf& sums_out) {
    if (device_sums)
      device_sums->evaluate(yg, rows, key_of, sums_out);
    else
      cpu_exact->evaluate(yg, rows, key_of, sums_out);
  };
  auto forget = [&](const std::vector<int>& rows) {
    if (cpu_exact) cpu_exact->forget(rows);
  };
  timer.lap("refinement: groups + index");
  Eigen::MatrixXf out(g, dim + 1);
  std::vector<int> active(g);
  std::iota(active.begin(), active.end(), 0);
  const float tol2 = static_cast<float>(params.convergence * params.convergence);
  // Trajectories that meet go on as one (Carreira-Perpinan's basin acceleration): a group whose
  // step lands in a cell (a fifth of the merge radius, the cells of groupModes) that another
  // group's trajectory went through follows that group from then on. Mean shift collapses
  // trajectories onto few ridges and modes, so most groups stop after a few exact steps.
  std::vector<int> leader(g);
  std::iota(leader.begin(), leader.end(), 0);
  auto root = [&](int r) {
    while (leader[r] != r) r = leader[r];
    return r;
  };
  const float visit_cell = static_cast<float>(params.merge_radius / 5.0);
  std::unordered_map<std::string, int> visited;
  auto claim = [&](int r) {  // true when r now follows another group
    for (int c = 0; c < dim; ++c) {
      const int q = static_cast<int>(std::floor(yg(r, c) * space.metric_plain[c] / visit_cell));
      std::memcpy(&key[sizeof(int) * c], &q, sizeof(int));
    }
    key.back() = key_of.empty() ? 0 : key_of[r];
    const auto [it, fresh] = visited.emplace(key, r);
    if (fresh) return false;
    const int other = root(it->second);
    if (other == r) return false;
    leader[r] = other;
    return true;
  };
  std::vector<int> start;
  for (int r : active)
    if (!claim(r)) start.push_back(r);
  active.swap(start);
  long evaluations = 0;
  int iterations = 0;
  for (int it = 0; it < params.refine_iterations && !active.empty(); ++it) {
    if (progress && it == 0) {
      // The first step of every group is most of the work: it is summed a slice of the groups at
      // a time, so that the progress moves (each group's sums do not depend on the others').
      constexpr std::size_t kSlice = 8192;
      progress->begin("first exact steps", active.size());
      for (std::size_t a = 0; a < active.size(); a += kSlice) {
        const std::vector<int> slice(active.begin() + a,
                                     active.begin() + std::min(active.size(), a + kSlice));
        evaluate(slice, out);
        progress->update(std::min(active.size(), a + kSlice));
      }
      progress->end();
    } else {
      evaluate(active, out);
    }
    evaluations += static_cast<long>(active.size());
    ++iterations;
    std::vector<int> still, stopped;
    for (int r : active) {
      const float den = out(r, dim);
      if (!(den > 0.0f)) {
        stopped.push_back(r);
        continue;
      }
      const Eigen::RowVectorXf next = out.row(r).head(dim) / den;
      const float step2 = (next - yg.row(r)).cwiseProduct(space.metric_plain).squaredNorm();
      yg.row(r) = next;
      if (!(step2 < tol2) && !claim(r)) still.push_back(r);
      else stopped.push_back(r);
    }
    forget(stopped);  // their neighbour lists
    active.swap(still);
  }
  forget(active);
  for (int r = 0; r < g; ++r) yg.row(r) = yg.row(root(r)).eval();
  for (Eigen::Index i = 0; i < n; ++i) y.row(i) = yg.row(group_of[i]);
  timer.lap("refinement: exact steps");
  if (timer.on())
    std::fprintf(stderr,
                 "[mean shift] refinement: %d groups, %ld exact steps, %ld tree searches, %d "
                 "iterations, %zu not converged%s\n",
                 g, evaluations, cpu_exact ? cpu_exact->searches() : 0L, iterations, active.size(),
                 device_sums ? " (sums on the device)" : "");
}

/** Starting points of the Gaussian kd-tree backend (Sect. 3.3): the cells of the filter's tree
 * (its leaves, N/M points each), split by the keypoint flag because a keypoint's query sums with
 * the pair rule of Eq. 5. start_of[i] is the start of point i, y0 the starts (cell means, raw
 * coordinates), start_key their keypoint flag (empty without keypoints). */
const filters::GaussianKdTree& cellStarts(const JointSpace& space, const JointKernelSum& sums,
                                          filters::GaussianKdTree& own, std::vector<int>& start_of,
                                          std::vector<int>& cell_start, Eigen::MatrixXf& y0,
                                          std::vector<char>& start_key) {
  const Eigen::Index n = space.z.rows();
  const int dim = static_cast<int>(space.z.cols());
  // Without the pair rule the sums' own tree is over the points in the plain metric: reuse it.
  const filters::GaussianKdTree* found = sums.cellTree();
  if (!found) own.build((space.z.array().rowwise() * space.metric_plain.array()).matrix());
  const filters::GaussianKdTree& tree = found ? *found : own;
  const bool keys = space.has_keypoints;
  cell_start.assign(tree.numSamples() * (keys ? 2 : 1), -1);
  start_of.resize(n);
  int m = 0;
  for (Eigen::Index i = 0; i < n; ++i) {
    const std::size_t c = tree.leafOf(i) * (keys ? 2 : 1) + (keys && space.keypoint[i] ? 1 : 0);
    if (cell_start[c] < 0) cell_start[c] = m++;
    start_of[i] = cell_start[c];
  }
  Eigen::MatrixXd sum = Eigen::MatrixXd::Zero(dim, m);
  std::vector<int> count(m, 0);
  for (Eigen::Index i = 0; i < n; ++i) {
    sum.col(start_of[i]) += space.z.row(i).transpose().cast<double>();
    ++count[start_of[i]];
  }
  y0.resize(m, dim);
  for (int r = 0; r < m; ++r) y0.row(r) = (sum.col(r) / count[r]).transpose().cast<float>();
  start_key.assign(keys ? m : 0, 0);
  if (keys)
    for (Eigen::Index i = 0; i < n; ++i) start_key[start_of[i]] = space.keypoint[i];
  return tree;
}

/** The paper method's iteration on the CPU: Eq. 9 until it stops; y the end points (one row per
 * data point), end_density the kernel sum there. The exact backend iterates every point; the
 * Gaussian kd-tree backend iterates the M cells of its tree, each from the mean of its points,
 * and every point takes its cell's end point: the paper's Sect. 3.3, N/M times fewer queries. */
void seekModesCpu(const JointSpace& space, const MeanShiftParams& params, Eigen::MatrixXf& y,
                  Eigen::VectorXf& end_density, std::unique_ptr<JointKernelSum>& sums_out,
                  Eigen::VectorXf& point_density, Progress* progress,
                  DeviceExactSums* device_sums = nullptr) {
  const Eigen::Index n = space.z.rows();
  const int dim = static_cast<int>(space.z.cols());
  StageTimer timer;
  // The exact backend's sums on a device (device_sums): the iteration below is the same, and
  // sums_out stays empty.
  if (params.backend != MeanShiftBackend::Exact) device_sums = nullptr;
  if (!device_sums)
    sums_out = std::make_unique<JointKernelSum>(space, homogeneousValues(space), params);
  // The tree's build and blur report their own times: the walk's below starts here.
  timer.restart();
  auto evaluate = [&](const Eigen::MatrixXf& q, const std::vector<int>& rows,
                      const std::vector<char>& q_key, Eigen::MatrixXf& out) {
    if (device_sums)
      device_sums->evaluate(q, rows, q_key, out);
    else
      sums_out->evaluate(q, rows, q_key, out);
  };
  const bool cells = params.backend == MeanShiftBackend::GaussianKdTree && params.iterate_cells;
  std::vector<int> start_of, cell_start;
  std::vector<char> start_key;
  Eigen::MatrixXf ys;  // the iterated rows: points (exact) or cells (Gaussian kd-tree)
  filters::GaussianKdTree own(params.gkdtree);
  const filters::GaussianKdTree* tree = nullptr;
  if (cells) {
    tree = &cellStarts(space, *sums_out, own, start_of, cell_start, ys, start_key);
  } else {
    ys = space.z;
    if (space.has_keypoints) start_key = space.keypoint;
  }
  const Eigen::Index m = ys.rows();
  std::vector<int> leader(m);
  std::iota(leader.begin(), leader.end(), 0);
  auto root = [&](int r) {
    while (leader[r] != r) r = leader[r];
    return r;
  };
  Eigen::MatrixXf out(m, dim + 1);
  Eigen::VectorXf start_density = Eigen::VectorXf::Zero(m);
  std::vector<int> active(m);
  std::iota(active.begin(), active.end(), 0);
  const float tol2 = static_cast<float>(params.convergence * params.convergence);
  if (progress) progress->begin("mean shift iterations", params.max_iterations);
  for (int it = 0; it < params.max_iterations && !active.empty(); ++it) {
    // Eq. 10: homogeneous coordinates, so the last column is the denominator of Eq. 8.
    evaluate(ys, active, start_key, out);
    // The density at the points (a cell's points: at their mean), for the saddles.
    if (it == 0) start_density = out.col(dim);
    std::vector<char> done(active.size(), 0);
    std::vector<int> entered(cells ? active.size() : 0, -1);
#pragma omp parallel for schedule(static)
    for (std::size_t a = 0; a < active.size(); ++a) {
      const int r = active[a];
      const float den = out(r, dim);
      if (!(den > 0.0f)) {
        done[a] = 1;
        continue;
      }
      const Eigen::RowVectorXf next = out.row(r).head(dim) / den;
      const float step2 = (next - ys.row(r)).cwiseProduct(space.metric_plain).squaredNorm();
      ys.row(r) = next;
      done[a] = step2 < tol2;
      if (cells && !done[a]) {
        const Eigen::RowVectorXf scaled = next.cwiseProduct(space.metric_plain);
        const int leaf = tree->leafContaining(scaled.data());
        entered[a] = cell_start[static_cast<std::size_t>(leaf) * (space.has_keypoints ? 2 : 1) +
                                (space.has_keypoints && start_key[r] ? 1 : 0)];
      }
    }
    std::vector<int> still;
    for (std::size_t a = 0; a < active.size(); ++a) {
      if (done[a]) continue;
      // A trajectory that enters another cell goes on as that cell's (whose points share one
      // mode already): the filter phase becomes a walk over cells, each taken once.
      if (cells && entered[a] >= 0) {
        const int other = root(entered[a]);
        if (other != active[a]) {
          leader[active[a]] = other;
          continue;
        }
      }
      still.push_back(active[a]);
    }
    active.swap(still);
    if (progress) progress->update(it + 1);
  }
  if (progress) progress->end(std::to_string(active.size()) + (cells ? " cells" : " points") +
                              " not converged");
  for (Eigen::Index r = 0; r < m; ++r) ys.row(r) = ys.row(root(static_cast<int>(r))).eval();
  timer.lap("iteration (walk over cells)");
  if (params.backend == MeanShiftBackend::GaussianKdTree && params.refine_iterations > 0) {
    refineEndPoints(space, params, start_key, ys);
    timer.lap("exact refinement");
  }
  // Density at the end points, to visit them from the highest.
  std::vector<int> all(m);
  std::iota(all.begin(), all.end(), 0);
  evaluate(ys, all, start_key, out);
  timer.lap("density at end points");
  if (!cells) {
    y = std::move(ys);
    end_density = out.col(dim);
    point_density = start_density;
    return;
  }
  y.resize(n, dim);
  end_density.resize(n);
  point_density.resize(n);
  for (Eigen::Index i = 0; i < n; ++i) {
    y.row(i) = ys.row(start_of[i]);
    end_density[i] = out(start_of[i], dim);
    point_density[i] = start_density[start_of[i]];
  }
}

/** Modes from the end points y (one row per data point): end points grouped into modes, tiny
 * clusters absorbed by the neighbour they share most k-NN edges with; flat the clusters, modes
 * one row per cluster. */
void groupAndAbsorb(const JointSpace& space, const std::vector<int>& graph, int k,
                    const MeanShiftParams& params, const Eigen::MatrixXf& y,
                    const Eigen::VectorXf& end_density, std::vector<int>& flat,
                    Eigen::MatrixXf& modes, int& num_clusters) {
  StageTimer timer;
  const Eigen::Index n = y.rows();
  const int dim = static_cast<int>(y.cols());
  std::vector<int> mode_rep;  // point whose end point is the mode
  groupModes(y, space.metric_plain, end_density, params.merge_radius, flat, mode_rep);
  timer.lap("mode grouping");
  int nm = static_cast<int>(mode_rep.size());

  // Absorb tiny clusters into the neighbour they share most k-NN edges with, smallest first.
  const int min_size = params.min_cluster_size > 0
                           ? params.min_cluster_size
                           : std::max(1, static_cast<int>(0.002 * static_cast<double>(n)));
  std::vector<long> size(nm, 0);
  for (int c : flat) ++size[c];
  // Symmetric edge counts (the k-NN graph is not): the absorption below removes a cluster from
  // the lists of its neighbours, and a one-sided entry would survive as a stale neighbour that a
  // later absorption could follow into a cycle of targets.
  // Flat lists sorted by neighbour id (pairs counted from a sorted list of the cross edges, not
  // one std::map insertion per edge: 8M edges at 800k points).
  using Edge = std::pair<int, long>;
  std::vector<std::vector<Edge>> adj(nm);
  {
    std::vector<std::uint64_t> cross;
    for (Eigen::Index i = 0; i < n; ++i)
      for (int m = 0; m < k; ++m) {
        const int j = graph[i * k + m];
        if (j >= 0 && flat[j] != flat[i]) cross.push_back(detail::pairKey(flat[i], flat[j]));
      }
    std::sort(cross.begin(), cross.end());
    for (std::size_t e = 0; e < cross.size();) {
      std::size_t f = e;
      while (f < cross.size() && cross[f] == cross[e]) ++f;
      const int a = detail::pairFirst(cross[e]), b = detail::pairSecond(cross[e]);
      const long cnt = static_cast<long>(f - e);
      adj[a].push_back({b, cnt});  // a < b and keys ascending: both lists stay sorted
      adj[b].push_back({a, cnt});
      e = f;
    }
    for (auto& list : adj) std::sort(list.begin(), list.end());
  }
  auto find = [](std::vector<Edge>& list, int id) {
    return std::lower_bound(list.begin(), list.end(), Edge(id, std::numeric_limits<long>::min()));
  };
  std::vector<int> target(nm);
  std::iota(target.begin(), target.end(), 0);
  // Smallest eligible cluster first (ties: lowest id), from a min-heap with lazy deletion: an
  // entry is stale when its cluster was absorbed or has grown since. A cluster without k-NN
  // edges is dropped and pushed again when it gains one (a neighbour absorbed a cluster next to
  // it). O(C log C) instead of a scan over all clusters per absorption.
  using Entry = std::pair<long, int>;
  std::priority_queue<Entry, std::vector<Entry>, std::greater<Entry>> heap;
  for (int m = 0; m < nm; ++m)
    if (size[m] < min_size) heap.push({size[m], m});
  while (!heap.empty()) {
    const auto [sz, c] = heap.top();
    heap.pop();
    if (target[c] != c || size[c] != sz || adj[c].empty()) continue;
    int b = -1;
    long best = -1;
    for (const auto& [nb, cnt] : adj[c])
      if (cnt > best) best = cnt, b = nb;
    target[c] = b;
    size[b] += size[c];
    size[c] = 0;
    for (const auto& [nb, cnt] : adj[c]) {
      if (nb == b) continue;
      // In nb's list, c's entry becomes (or adds to) b's.
      std::vector<Edge>& list = adj[nb];
      list.erase(find(list, c));
      auto at = find(list, b);
      if (at != list.end() && at->first == b) at->second += cnt;
      else list.insert(at, {b, cnt});
      if (size[nb] < min_size) heap.push({size[nb], nb});
    }
    // b's list: merged with c's (both sorted), without b and c.
    std::vector<Edge> merged;
    merged.reserve(adj[b].size() + adj[c].size());
    auto x = adj[b].begin(), y = adj[c].begin();
    while (x != adj[b].end() || y != adj[c].end()) {
      Edge e;
      if (y == adj[c].end() || (x != adj[b].end() && x->first < y->first)) e = *x++;
      else if (x == adj[b].end() || y->first < x->first) e = *y++;
      else e = {x->first, x->second + y->second}, ++x, ++y;
      if (e.first != b && e.first != c) merged.push_back(e);
    }
    adj[b].swap(merged);
    std::vector<Edge>().swap(adj[c]);
    if (size[b] < min_size) heap.push({size[b], b});
  }
  // Absorption chains can be thousands long (many tiny clusters absorbed one into the next):
  // follow each once, with path compression, instead of once per point.
  auto root = [&](int c) { return findRoot(target, c); };
  // Final ids by decreasing mode density (mode order), modes from the densest merged mode.
  std::vector<int> final_id(nm, -1);
  num_clusters = 0;
  std::vector<int> final_rep;
  for (int m = 0; m < nm; ++m) {
    const int r = root(m);
    if (final_id[r] < 0) {
      final_id[r] = num_clusters++;
      final_rep.push_back(mode_rep[r]);
    }
  }
  for (int m = 0; m < nm; ++m) final_id[m] = final_id[root(m)];
  for (Eigen::Index i = 0; i < n; ++i) flat[i] = final_id[flat[i]];
  modes.resize(num_clusters, dim);
  for (int c = 0; c < num_clusters; ++c) modes.row(c) = y.row(final_rep[c]);
  timer.lap("absorption");
}

/** One round of MeanShiftParams::exact_borders: the points on a border between two clusters of
 * the labels flat (a k-NN edge of their frame, either way, to another cluster) that have not run
 * yet (`done`) follow their own exact mean-shift trajectories from their own positions: y's rows
 * of these points become their end points, and `done` marks them. Returns the points run,
 * ascending. */
std::vector<int> exactBorderRound(const JointSpace& space, const std::vector<int>& graph, int k,
                                  const MeanShiftParams& params, const std::vector<int>& flat,
                                  std::vector<char>& done, Eigen::MatrixXf& y, Progress* progress,
                                  DeviceExactSums* device_sums) {
  const Eigen::Index n = y.rows();
  std::vector<char> border(n, 0);
  for (Eigen::Index i = 0; i < n; ++i)
    for (int m = 0; m < k; ++m) {
      const int j = graph[i * k + m];
      if (j >= 0 && flat[j] != flat[i]) border[i] = border[j] = 1;
    }
  std::vector<int> rows;
  for (Eigen::Index i = 0; i < n; ++i)
    if (border[i] && !done[i]) rows.push_back(static_cast<int>(i));
  if (rows.empty()) return rows;
  Eigen::MatrixXf yb(rows.size(), y.cols());
  std::vector<char> keys(space.has_keypoints ? rows.size() : 0);
  for (std::size_t b = 0; b < rows.size(); ++b) {
    yb.row(b) = space.z.row(rows[b]);
    if (space.has_keypoints) keys[b] = space.keypoint[rows[b]];
  }
  // From a data point the exact trajectory has its whole way to go, not only the last steps.
  MeanShiftParams exact_params = params;
  exact_params.refine_iterations = std::max(params.refine_iterations, params.max_iterations);
  refineEndPoints(space, exact_params, keys, yb, progress, device_sums);
  for (std::size_t b = 0; b < rows.size(); ++b) {
    y.row(rows[b]) = yb.row(b);
    done[rows[b]] = 1;
  }
  return rows;
}

/** Paper's method: mean shift of every point (Eq. 9) until it stops (on the CPU or the device),
 * then modes. */
void runPaper(const JointSpace& space, const std::vector<int>& graph, int k,
              const MeanShiftParams& params, MeanShiftDeviceBackend* device, std::vector<int>& flat,
              Eigen::MatrixXf& modes, int& num_clusters, std::unique_ptr<JointKernelSum>& sums,
              std::unique_ptr<DeviceExactSums>& device_sums, Eigen::VectorXf& point_density,
              Progress* progress) {
  const Eigen::Index n = space.z.rows();
  const int dim = static_cast<int>(space.z.cols());
  const std::vector<char> no_keys;
  const std::vector<char>& keys = space.has_keypoints ? space.keypoint : no_keys;
  Eigen::MatrixXf y;
  Eigen::VectorXf end_density;
  const bool gkd = params.backend == MeanShiftBackend::GaussianKdTree;
  // The exact sums on the device, where it offers them: the exact backend's iteration (and its
  // result's densities: kept for the caller), the refinement's exact steps and the border
  // rounds'.
  device_sums.reset();
  const bool need_sums = device && (!gkd || params.refine_iterations > 0 || params.exact_borders);
  if (need_sums && !gkd) {
    StageTimer upload_timer;
    device_sums = device->exactSums(space.z, space.metric_plain, space.metric_key, keys);
    upload_timer.lap("exact sums: data to the device");
  }
  if (device && gkd) {
    StageTimer timer;
    // The exact sums' data (ordered on the host, then uploaded) are made on a thread of their
    // own while the device iterates: the host mostly waits for the device there.
    std::future<std::unique_ptr<DeviceExactSums>> pending;
    if (need_sums)
      pending = std::async(std::launch::async, [&] {
        return device->exactSums(space.z, space.metric_plain, space.metric_key, keys);
      });
    if (progress) progress->begin("mean shift on " + device->name(), 1);
    device->seekModes(space.z, space.metric_plain, space.metric_key, keys, params, y, end_density);
    if (progress) progress->end();
    timer.lap("device iteration");
    if (pending.valid()) {
      device_sums = pending.get();
      timer.lap("exact sums: data to the device (beside the iteration)");
    }
    if (params.refine_iterations > 0) {
      refineEndPoints(space, params, keys, y, nullptr, device_sums.get());
      timer.restart();
      device->density(space.z, space.metric_plain, space.metric_key, keys, params, y, keys,
                      end_density);
      timer.lap("density at end points (device)");
    }
  } else {
    // The CPU's iteration; for the exact backend with its sums on the device when it has them.
    seekModesCpu(space, params, y, end_density, sums, point_density, progress, device_sums.get());
  }
  groupAndAbsorb(space, graph, k, params, y, end_density, flat, modes, num_clusters);
  if (params.exact_borders && gkd) {
    // The filter's labels are right but at the borders of its basins: exact trajectories for
    // the border points move a border by a ring of neighbours at a time, so rounds follow it
    // until it settles (each round runs only points that have not run yet: at most n in all).
    StageTimer border_timer;
    if (progress) progress->begin("exact border trajectories", 1);
    std::vector<char> done(n, 0);
    std::size_t total = 0;
    int rounds = 0;
    for (;;) {
      const auto rerun =
          exactBorderRound(space, graph, k, params, flat, done, y, progress, device_sums.get());
      if (rerun.empty()) break;
      total += rerun.size();
      ++rounds;
      // The re-run end points' densities (the order in which groupModes visits them): only
      // theirs, in a matrix of their own (the others' end points have not moved).
      const Eigen::Index r = static_cast<Eigen::Index>(rerun.size());
      Eigen::MatrixXf yr(r, dim);
      std::vector<char> kr(keys.empty() ? 0 : rerun.size());
      for (Eigen::Index b = 0; b < r; ++b) {
        yr.row(b) = y.row(rerun[b]);
        if (!keys.empty()) kr[b] = keys[rerun[b]];
      }
      if (device) {
        Eigen::VectorXf fr;
        device->density(space.z, space.metric_plain, space.metric_key, keys, params, yr, kr, fr);
        for (Eigen::Index b = 0; b < r; ++b) end_density[rerun[b]] = fr[b];
      } else {
        Eigen::MatrixXf out(r, dim + 1);
        std::vector<int> rows(rerun.size());
        std::iota(rows.begin(), rows.end(), 0);
        sums->evaluate(yr, rows, kr, out);
        for (Eigen::Index b = 0; b < r; ++b) end_density[rerun[b]] = out(b, dim);
      }
      groupAndAbsorb(space, graph, k, params, y, end_density, flat, modes, num_clusters);
    }
    border_timer.lap("exact border trajectories");
    if (progress)
      progress->end(std::to_string(total) + " of " + std::to_string(n) + " points, " +
                    std::to_string(rounds) + " rounds");
  }
  if (gkd) device_sums.reset();  // the filter's densities come from the device's filter
}

}  // namespace

void MeanShiftSegmentation::segment(SegmentationResult& result) {
  validate();
  const PointCloudSequence& seq = *sequence_;
  const int k = params_.neighbours;
  std::vector<int> flat;
  int num_clusters = 0;
  result = SegmentationResult();
  device_used_ = "cpu";
  fallback_reason_.clear();
  MeanShiftDeviceBackend* device = device_.get();
  // A device failure either propagates or, with the fall-back on, sends the rest of the stage to
  // the CPU (never a silent wrong result: the reason is kept for the caller to log).
  auto guarded = [&](const std::function<void(MeanShiftDeviceBackend*)>& work) {
    if (!device) return work(nullptr);
    // The failed try's open progress stages are closed before the CPU runs them again.
    const std::size_t depth = progress_ ? progress_->depth() : 0;
    try {
      work(device);
      device_used_ = device->name();
    } catch (const Error& e) {
      if (!cpu_fallback_) throw;
      if (progress_) progress_->abandon(depth);
      fallback_reason_ = e.what();
      device = nullptr;
      device_used_ = "cpu";
      work(nullptr);
    }
  };
  if (params_.method == MeanShiftMethod::Paper) {
    detail::StageTimer timer;
    const JointSpace space = detail::buildJointSpace(seq, signatures_, keypoints_, params_);
    timer.lap("joint space");
    const std::vector<int> graph = detail::knnGraph(seq, k);
    timer.lap("k-NN graph");
    // The CPU iteration leaves its kernel sums and the density at the points for the densities
    // of the result (no second filter over the data).
    std::unique_ptr<detail::JointKernelSum> sums;
    std::unique_ptr<DeviceExactSums> device_sums;  // the exact backend's, on the device
    Eigen::VectorXf point_density;
    guarded([&](MeanShiftDeviceBackend* d) {
      Eigen::MatrixXf modes;
      runPaper(space, graph, k, params_, d, flat, modes, num_clusters, sums, device_sums,
               point_density, progress_);
      result.modes = modes;
      // What ran: the device's filter, the CPU's (0 from the exact backend's sums), or none.
      result.sampling_factor = d ? d->samplingFactor() : sums ? sums->samplingFactor() : 0.0;
    });
    timer.restart();
    guarded([&](MeanShiftDeviceBackend* d) {
      // The iteration's sums where they ran (on the CPU, or its fall-back, or the exact
      // backend's on the device): the densities reuse them and the density at the points.
      if (sums) {
        detail::finishResult(space, flat, num_clusters, graph, k, *sums, point_density,
                             result);
      } else if (d && device_sums) {
        detail::finishResult(space, flat, num_clusters, graph, k, *device_sums, point_density,
                             result);
      } else {
        detail::finishResult(space, flat, num_clusters, graph, k, params_, true, result, d);
      }
    });
    timer.lap("densities + saddles");
  } else {
    detail::StageTimer timer;
    // A device with a MotionDevice fits the tracking's poses and computes the method's residual
    // and point-cost batches; the rest of the method runs on the CPU.
    auto motion = [&](MeanShiftDeviceBackend* d) {
      detail::runMotion(seq, params_, d ? d->motionDevice() : nullptr, flat, num_clusters,
                        result.merges, result.motions, progress_, beside_chains_);
    };
    if (device && device->motionDevice())
      guarded(motion);
    else
      motion(nullptr);
    timer.lap("motion method");
    if (!params_.record_densities && (!result.merges.empty() || num_clusters <= 1)) {
      result.num_clusters = num_clusters;
      result.mode_density.assign(static_cast<std::size_t>(std::max(num_clusters, 0)), 0.0);
      result.labels = detail::splitByFrame(flat, seq.offsets());
      return;
    }
    // Built after the tracking, so that the joint space (N x d floats) and the k-NN graph do not
    // add to the tracking's peak memory.
    const JointSpace space = detail::buildJointSpace(seq, signatures_, keypoints_, params_);
    timer.lap("joint space");
    const std::vector<int> graph = detail::knnGraph(seq, k);
    timer.lap("k-NN graph");
    guarded([&](MeanShiftDeviceBackend* d) {
      detail::finishResult(space, flat, num_clusters, graph, k, params_, false, result, d);
    });
    timer.lap("densities + saddles");
  }
}

void MeanShiftSegmentation::toPointIndices(const SegmentationResult& result,
                                           std::vector<pcl::PointIndices>& clusters) {
  clusters.assign(result.num_clusters, pcl::PointIndices());
  int offset = 0;
  for (const auto& frame : result.labels) {
    for (std::size_t j = 0; j < frame.size(); ++j)
      if (frame[j] >= 0) clusters[frame[j]].indices.push_back(offset + static_cast<int>(j));
    offset += static_cast<int>(frame.size());
  }
}

void MeanShiftSegmentation::extract(std::vector<pcl::PointIndices>& clusters) {
  SegmentationResult result;
  segment(result);
  toPointIndices(result, clusters);
}

}  // namespace segmentation
}  // namespace pcl_animseg
