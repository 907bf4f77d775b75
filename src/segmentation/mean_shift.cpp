#include "mean_shift_internal.h"

#include <pcl/kdtree/kdtree_flann.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/progress.h>

#include <flann/flann.hpp>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <map>
#include <numeric>
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
  if (!(p.merge_radius > 0.0)) throw Error("mean shift: merge radius must be positive");
  if (p.min_cluster_size < 0 || p.neighbours < 1 || p.patches < 0 || p.target_clusters < 0)
    throw Error("mean shift: cluster size, neighbours, patches and target must be >= 0 (k >= 1)");
  if (!(p.motion_threshold > 0.0)) throw Error("mean shift: motion threshold must be positive");
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
};

namespace {

// Exact reference: FLANN kd-tree (single tree, exact search) radius search at 3 bandwidths
// (the Gaussian is 1.1% there), then the exact kernel.
class ExactBackend : public JointKernelSum::Backend {
 public:
  ExactBackend(const Eigen::MatrixXf& x, const Eigen::MatrixXf& values)
      : x_(x), values_(values.transpose()) {
    index_ = std::make_unique<flann::Index<flann::L2<float>>>(
        flann::Matrix<float>(x_.data(), x_.rows(), x_.cols()),
        flann::KDTreeSingleIndexParams(15));
    index_->buildIndex();
  }
  void evaluate(const Eigen::MatrixXf& q, const std::vector<int>& rows,
                Eigen::MatrixXf& out) const override {
    const int v = static_cast<int>(values_.rows());
    const int nr = static_cast<int>(rows.size());
    const float r2 = 9.0f;
#pragma omp parallel
    {
      std::vector<std::vector<int>> idx(1);
      std::vector<std::vector<float>> dst(1);
      std::vector<float> qb(q.cols());
      Eigen::VectorXd acc(v);
      flann::SearchParams sp(flann::FLANN_CHECKS_UNLIMITED);
      sp.cores = 1;
      sp.sorted = false;
#pragma omp for schedule(dynamic, 64)
      for (int r = 0; r < nr; ++r) {
        for (Eigen::Index k = 0; k < q.cols(); ++k) qb[k] = q(rows[r], k);
        flann::Matrix<float> qm(qb.data(), 1, qb.size());
        // FLANN's L2 is the squared distance, so the radius is squared too.
        index_->radiusSearch(qm, idx, dst, r2, sp);
        acc.setZero();
        for (std::size_t m = 0; m < idx[0].size(); ++m)
          acc += std::exp(-0.5 * dst[0][m]) * values_.col(idx[0][m]).cast<double>();
        for (int c = 0; c < v; ++c) out(rows[r], c) += static_cast<float>(acc[c]);
      }
    }
  }

 private:
  Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> x_;
  Eigen::MatrixXf values_;  // v x n
  std::unique_ptr<flann::Index<flann::L2<float>>> index_;
};

class GkdBackend : public JointKernelSum::Backend {
 public:
  GkdBackend(const Eigen::MatrixXf& x, const Eigen::MatrixXf& values,
             const filters::GaussianKdTreeParams& params)
      : tree_(params) {
    tree_.build(x);
    tree_.splatBlur(values, sample_values_);
  }
  void evaluate(const Eigen::MatrixXf& q, const std::vector<int>& rows,
                Eigen::MatrixXf& out) const override {
    Eigen::MatrixXf tmp(out.rows(), out.cols());
    tree_.slice(sample_values_, q, rows, tmp);
    for (int r : rows) out.row(r) += tmp.row(r);
  }

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
                               const MeanShiftParams& params)
    : space_(space), value_count_(static_cast<int>(values.cols())) {
  auto make = [&](const std::vector<Eigen::Index>& idx, bool key, int applies) {
    if (idx.empty()) return;
    const Eigen::RowVectorXf& m = key ? space.metric_key : space.metric_plain;
    Eigen::MatrixXf x(idx.size(), space.z.cols());
    Eigen::MatrixXf v(idx.size(), values.cols());
    for (std::size_t i = 0; i < idx.size(); ++i) {
      x.row(i) = space.z.row(idx[i]).cwiseProduct(m);
      v.row(i) = values.row(idx[i]);
    }
    auto g = std::make_unique<Group>();
    g->key_metric = key;
    g->applies_to = applies;
    if (params.backend == MeanShiftBackend::Exact)
      g->backend = std::make_unique<ExactBackend>(x, v);
    else
      g->backend = std::make_unique<GkdBackend>(x, v, params.gkdtree);
    groups_.push_back(std::move(g));
  };
  std::vector<Eigen::Index> plain, key;
  for (Eigen::Index i = 0; i < space.z.rows(); ++i)
    (space.has_keypoints && space.keypoint[i] ? key : plain).push_back(i);
  make(plain, false, 0);
  make(key, false, 1);  // Eq. 6 between a keypoint and a non-keypoint query
  make(key, true, 2);   // Eq. 5 between two keypoints
}

JointKernelSum::~JointKernelSum() = default;

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
  for (std::size_t t = 0; t < seq.size(); ++t) {
    const auto& cloud = seq.frame(t);
    if (cloud->size() < 2) continue;
    pcl::KdTreeFLANN<pcl::PointNormal> tree;
    tree.setInputCloud(cloud);
    const int kk = std::min<int>(k + 1, static_cast<int>(cloud->size()));
    const int n = static_cast<int>(cloud->size());
#pragma omp parallel
    {
      std::vector<int> idx;
      std::vector<float> d2;
#pragma omp for schedule(static)
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

void finishResult(const JointSpace& space, const std::vector<int>& flat, int num_clusters,
                  const std::vector<int>& graph, int k, const MeanShiftParams& params,
                  const PointCloudSequence& seq, bool modes_known, SegmentationResult& result) {
  const Eigen::Index n = space.z.rows();
  const Eigen::MatrixXf ones = Eigen::MatrixXf::Ones(n, 1);
  JointKernelSum density(space, ones, params);
  std::vector<int> all(n);
  std::iota(all.begin(), all.end(), 0);
  Eigen::MatrixXf f(n, 1);
  density.evaluate(space.z, all, space.keypoint, f);
  result.num_clusters = num_clusters;
  if (!modes_known) {
    result.modes.resize(num_clusters, space.z.cols());
    result.mode_density.assign(num_clusters, -1.0);
    for (Eigen::Index i = 0; i < n; ++i) {
      const int c = flat[i];
      if (c < 0) continue;
      if (f(i, 0) > result.mode_density[c]) {
        result.mode_density[c] = f(i, 0);
        result.modes.row(c) = space.z.row(i);
      }
    }
  } else {
    // Density at the modes themselves (Eq. 4), queried as plain points.
    Eigen::MatrixXf fm(num_clusters, 1);
    std::vector<int> rows(num_clusters);
    std::iota(rows.begin(), rows.end(), 0);
    density.evaluate(result.modes, rows, {}, fm);
    result.mode_density.resize(num_clusters);
    for (int c = 0; c < num_clusters; ++c) result.mode_density[c] = fm(c, 0);
    // The filter is approximate: keep a mode at least as dense as its cluster's points, so that
    // persistence (mode minus saddle, Eq. 12) is never negative.
    for (Eigen::Index i = 0; i < n; ++i)
      if (flat[i] >= 0)
        result.mode_density[flat[i]] = std::max<double>(result.mode_density[flat[i]], f(i, 0));
  }
  // Saddle between adjacent clusters: the highest min(f_i, f_j) over k-NN pairs across them.
  std::map<std::pair<int, int>, double> saddle;
  for (Eigen::Index i = 0; i < n; ++i) {
    const int a = flat[i];
    if (a < 0) continue;
    for (int m = 0; m < k; ++m) {
      const int j = graph[i * k + m];
      if (j < 0) continue;
      const int b = flat[j];
      if (b < 0 || b == a) continue;
      const std::pair<int, int> key(std::min(a, b), std::max(a, b));
      const double s = std::min(f(i, 0), f(j, 0));
      auto it = saddle.find(key);
      if (it == saddle.end()) saddle.emplace(key, s);
      else it->second = std::max(it->second, s);
    }
  }
  result.saddles.clear();
  for (const auto& [key, s] : saddle) result.saddles.push_back({key.first, key.second, s});
  result.labels.assign(seq.size(), {});
  for (std::size_t t = 0; t < seq.size(); ++t)
    result.labels[t].assign(flat.begin() + space.offsets[t], flat.begin() + space.offsets[t + 1]);
}

}  // namespace detail

namespace {

using detail::JointKernelSum;
using detail::JointSpace;

/** Paper's method: mean shift of every point (Eq. 9) until it stops, then modes. */
void runPaper(const JointSpace& space, const std::vector<int>& graph, int k,
              const MeanShiftParams& params, std::vector<int>& flat, Eigen::MatrixXf& modes,
              int& num_clusters, Progress* progress) {
  const Eigen::Index n = space.z.rows();
  const int dim = static_cast<int>(space.z.cols());
  Eigen::MatrixXf values(n, dim + 1);
  values.leftCols(dim) = space.z;
  values.col(dim).setOnes();
  JointKernelSum sums(space, values, params);
  Eigen::MatrixXf y = space.z;
  Eigen::MatrixXf out(n, dim + 1);
  std::vector<int> active(n);
  std::iota(active.begin(), active.end(), 0);
  const float tol2 = static_cast<float>(params.convergence * params.convergence);
  if (progress) progress->begin("mean shift iterations", params.max_iterations);
  for (int it = 0; it < params.max_iterations && !active.empty(); ++it) {
    // Eq. 10: homogeneous coordinates, so the last column is the denominator of Eq. 8.
    sums.evaluate(y, active, space.keypoint, out);
    std::vector<char> done(active.size(), 0);
#pragma omp parallel for schedule(static)
    for (std::size_t a = 0; a < active.size(); ++a) {
      const int r = active[a];
      const float den = out(r, dim);
      if (!(den > 0.0f)) {
        done[a] = 1;
        continue;
      }
      const Eigen::RowVectorXf next = out.row(r).head(dim) / den;
      const float step2 = (next - y.row(r)).cwiseProduct(space.metric_plain).squaredNorm();
      y.row(r) = next;
      done[a] = step2 < tol2;
    }
    std::vector<int> still;
    for (std::size_t a = 0; a < active.size(); ++a)
      if (!done[a]) still.push_back(active[a]);
    active.swap(still);
    if (progress) progress->update(it + 1);
  }
  if (progress) progress->end(std::to_string(active.size()) + " points not converged");

  // Density at the end points, to visit them from the highest.
  std::vector<int> all(n);
  std::iota(all.begin(), all.end(), 0);
  sums.evaluate(y, all, space.keypoint, out);
  // Group end points that coincide (cells of a fifth of the merge radius), then merge groups
  // greedily from the densest: a group within the merge radius of a kept mode joins it.
  const Eigen::MatrixXf ys = y.array().rowwise() * space.metric_plain.array();
  const float cell = static_cast<float>(params.merge_radius / 5.0);
  std::unordered_map<std::string, int> cell_group;
  std::vector<int> group_of(n);
  std::vector<int> group_rep;
  std::string key(sizeof(int) * dim, '\0');
  for (Eigen::Index i = 0; i < n; ++i) {
    for (int c = 0; c < dim; ++c) {
      const int q = static_cast<int>(std::floor(ys(i, c) / cell));
      std::memcpy(&key[sizeof(int) * c], &q, sizeof(int));
    }
    auto it = cell_group.find(key);
    if (it == cell_group.end()) {
      it = cell_group.emplace(key, static_cast<int>(group_rep.size())).first;
      group_rep.push_back(static_cast<int>(i));
    } else if (out(i, dim) > out(group_rep[it->second], dim)) {
      group_rep[it->second] = static_cast<int>(i);
    }
    group_of[i] = it->second;
  }
  std::vector<int> order(group_rep.size());
  std::iota(order.begin(), order.end(), 0);
  std::stable_sort(order.begin(), order.end(), [&](int a, int b) {
    return out(group_rep[a], dim) > out(group_rep[b], dim);
  });
  const float r2 = static_cast<float>(params.merge_radius * params.merge_radius);
  std::vector<int> mode_rep;  // point whose end point is the mode
  std::vector<int> group_mode(group_rep.size(), -1);
  for (int g : order) {
    const auto yg = ys.row(group_rep[g]);
    int found = -1;
    for (std::size_t m = 0; m < mode_rep.size() && found < 0; ++m)
      if ((ys.row(mode_rep[m]) - yg).squaredNorm() < r2) found = static_cast<int>(m);
    if (found < 0) {
      found = static_cast<int>(mode_rep.size());
      mode_rep.push_back(group_rep[g]);
    }
    group_mode[g] = found;
  }
  flat.resize(n);
  for (Eigen::Index i = 0; i < n; ++i) flat[i] = group_mode[group_of[i]];
  int nm = static_cast<int>(mode_rep.size());

  // Absorb tiny clusters into the neighbour they share most k-NN edges with, smallest first.
  const int min_size = params.min_cluster_size > 0
                           ? params.min_cluster_size
                           : std::max(1, static_cast<int>(0.002 * static_cast<double>(n)));
  std::vector<long> size(nm, 0);
  for (int c : flat) ++size[c];
  std::vector<std::map<int, long>> adj(nm);
  for (Eigen::Index i = 0; i < n; ++i)
    for (int m = 0; m < k; ++m) {
      const int j = graph[i * k + m];
      if (j >= 0 && flat[j] != flat[i]) ++adj[flat[i]][flat[j]];
    }
  std::vector<int> target(nm);
  std::iota(target.begin(), target.end(), 0);
  for (;;) {
    int c = -1;
    for (int m = 0; m < nm; ++m)
      if (target[m] == m && size[m] < min_size && !adj[m].empty() && (c < 0 || size[m] < size[c]))
        c = m;
    if (c < 0) break;
    int b = -1;
    long best = -1;
    for (const auto& [nb, cnt] : adj[c])
      if (cnt > best) best = cnt, b = nb;
    target[c] = b;
    size[b] += size[c];
    size[c] = 0;
    for (const auto& [nb, cnt] : adj[c]) {
      adj[nb].erase(c);
      if (nb == b) continue;
      adj[b][nb] += cnt;
      adj[nb][b] += cnt;
    }
    adj[b].erase(c);
    adj[c].clear();
  }
  auto root = [&](int c) {
    while (target[c] != c) c = target[c];
    return c;
  };
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
  for (Eigen::Index i = 0; i < n; ++i) flat[i] = final_id[root(flat[i])];
  modes.resize(num_clusters, dim);
  for (int c = 0; c < num_clusters; ++c) modes.row(c) = y.row(final_rep[c]);
}

}  // namespace

void MeanShiftSegmentation::segment(SegmentationResult& result) {
  validate();
  const PointCloudSequence& seq = *sequence_;
  const JointSpace space = detail::buildJointSpace(seq, signatures_, keypoints_, params_);
  const int k = params_.neighbours;
  const std::vector<int> graph = detail::knnGraph(seq, k);
  std::vector<int> flat;
  int num_clusters = 0;
  result = SegmentationResult();
  if (params_.method == MeanShiftMethod::Paper) {
    Eigen::MatrixXf modes;
    runPaper(space, graph, k, params_, flat, modes, num_clusters, progress_);
    result.modes = modes;
    detail::finishResult(space, flat, num_clusters, graph, k, params_, seq, true, result);
  } else {
    detail::runMotion(seq, params_, flat, num_clusters, result.merges, progress_);
    detail::finishResult(space, flat, num_clusters, graph, k, params_, seq, false, result);
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
