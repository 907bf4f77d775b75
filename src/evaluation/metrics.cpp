#include <pcl_animseg/error.h>
#include <pcl_animseg/evaluation/metrics.h>

#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <sstream>
#include <unordered_map>
#include <unordered_set>

namespace pcl_animseg {
namespace evaluation {

namespace {

/** \brief Contingency table of two labelings, filled point by point.
 *
 * Labels are renamed to dense ids on the fly so that a cell is one 64-bit key; every count is an
 * integer and the pair counts are summed in long double, which is exact up to 2^64 — enough for
 * C(n, 2) with n in the billions, so pooled scores over long sequences do not lose precision. */
class Contingency {
 public:
  void add(int a, int b) {
    if (a < 0 || b < 0) return;
    const std::uint64_t ia = dense(a, ids_a_, rows_, last_a_, last_ia_);
    const std::uint64_t ib = dense(b, ids_b_, cols_, last_b_, last_ib_);
    ++rows_[ia];
    ++cols_[ib];
    ++cells_[(ia << 32) | ib];
    ++n_;
  }

  std::uint64_t size() const { return n_; }

  double ari() const {
    if (n_ < 2) return 0.0;
    long double index = 0, sum_a = 0, sum_b = 0;
    for (const auto& c : cells_) index += pairs(c.second);
    for (std::uint64_t r : rows_) sum_a += pairs(r);
    for (std::uint64_t c : cols_) sum_b += pairs(c);
    const long double total = pairs(n_);
    const long double expected = sum_a * sum_b / total;
    const long double max_index = 0.5L * (sum_a + sum_b);
    const long double denom = max_index - expected;
    // By AM-GM, denom == 0 only when sum_a == sum_b is 0 (both all singletons) or C(n,2) (both
    // one cluster): the partitions are then identical.
    if (denom == 0) return 1.0;
    return static_cast<double>((index - expected) / denom);
  }

  /** matchParts from this table, the first labelling predicted, the second true: per true part
   * (by label) the predicted part with the most shared points (ties to the lower label). */
  std::vector<PartMatch> matches() const {
    std::vector<int> label_a(ids_a_.size()), label_b(ids_b_.size());
    for (const auto& [label, id] : ids_a_) label_a[id] = label;
    for (const auto& [label, id] : ids_b_) label_b[id] = label;
    std::vector<std::uint64_t> best(cols_.size(), 0);
    std::vector<int> best_a(cols_.size(), -1);
    for (const auto& [key, count] : cells_) {
      const std::uint64_t ia = key >> 32, ib = key & 0xffffffffu;
      if (count > best[ib] || (count == best[ib] && label_a[ia] < label_a[best_a[ib]]))
        best[ib] = count, best_a[ib] = static_cast<int>(ia);
    }
    std::vector<PartMatch> out(cols_.size());
    for (std::size_t ib = 0; ib < cols_.size(); ++ib) {
      PartMatch& m = out[ib];
      const std::uint64_t in_pred = rows_[best_a[ib]], shared = best[ib];
      m.truth = label_b[ib];
      m.points = static_cast<std::size_t>(cols_[ib]);
      m.predicted = label_a[best_a[ib]];
      m.recall = static_cast<double>(shared) / static_cast<double>(cols_[ib]);
      m.precision = static_cast<double>(shared) / static_cast<double>(in_pred);
      m.iou = static_cast<double>(shared) / static_cast<double>(cols_[ib] + in_pred - shared);
    }
    std::sort(out.begin(), out.end(),
              [](const PartMatch& x, const PartMatch& y) { return x.truth < y.truth; });
    return out;
  }

 private:
  static long double pairs(std::uint64_t k) {
    return static_cast<long double>(k) * static_cast<long double>(k - (k > 0 ? 1 : 0)) / 2.0L;
  }
  // Consecutive points usually share a label, so the last lookup is cached.
  static std::uint64_t dense(int label, std::unordered_map<int, std::uint64_t>& ids,
                             std::vector<std::uint64_t>& sums, int& last, std::uint64_t& last_id) {
    if (label == last) return last_id;
    auto it = ids.find(label);
    if (it == ids.end()) {
      it = ids.emplace(label, sums.size()).first;
      sums.push_back(0);
    }
    last = label;
    last_id = it->second;
    return last_id;
  }

  std::unordered_map<int, std::uint64_t> ids_a_, ids_b_;
  std::vector<std::uint64_t> rows_, cols_;
  std::unordered_map<std::uint64_t, std::uint64_t> cells_;
  std::uint64_t n_ = 0;
  int last_a_ = -1, last_b_ = -1;
  std::uint64_t last_ia_ = 0, last_ib_ = 0;
};

std::string number(double v) {
  if (!std::isfinite(v)) return "null";
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.9g", v);
  return buf;
}

}  // namespace

double adjustedRandIndex(const std::vector<int>& a, const std::vector<int>& b) {
  if (a.size() != b.size())
    throw Error("adjustedRandIndex: labelings differ in length (" + std::to_string(a.size()) +
                " vs " + std::to_string(b.size()) + ")");
  Contingency table;
  for (std::size_t i = 0; i < a.size(); ++i) table.add(a[i], b[i]);
  return table.ari();
}

RigidFit kabsch(const Eigen::Matrix3Xd& src, const Eigen::Matrix3Xd& dst) {
  if (src.cols() != dst.cols())
    throw Error("kabsch: point sets differ in size (" + std::to_string(src.cols()) + " vs " +
                std::to_string(dst.cols()) + ")");
  RigidFit fit;
  const Eigen::Index n = src.cols();
  if (n == 0) return fit;
  const Eigen::Vector3d cs = src.rowwise().mean();
  const Eigen::Vector3d cd = dst.rowwise().mean();
  const Eigen::Matrix3d h = (src.colwise() - cs) * (dst.colwise() - cd).transpose();
  Eigen::JacobiSVD<Eigen::Matrix3d> svd(h, Eigen::ComputeFullU | Eigen::ComputeFullV);
  const Eigen::Matrix3d& u = svd.matrixU();
  const Eigen::Matrix3d& v = svd.matrixV();
  // Flipping the axis of the smallest singular value turns a reflection into the best proper
  // rotation (Kabsch 1976 / Umeyama 1991).
  Eigen::Vector3d d(1.0, 1.0, (v * u.transpose()).determinant() < 0.0 ? -1.0 : 1.0);
  fit.rotation = v * d.asDiagonal() * u.transpose();
  fit.translation = cd - fit.rotation * cs;
  const Eigen::Matrix3Xd residual = (fit.rotation * src).colwise() + fit.translation - dst;
  fit.rms = std::sqrt(residual.squaredNorm() / static_cast<double>(n));
  return fit;
}

int countParts(const std::vector<int>& labels) {
  std::unordered_set<int> seen;
  for (int l : labels)
    if (l >= 0) seen.insert(l);
  return static_cast<int>(seen.size());
}

double rigidityError(const std::vector<Eigen::Matrix3Xd>& positions,
                     const std::vector<int>& labels) {
  if (positions.empty()) return 0.0;
  const Eigen::Index n = positions[0].cols();
  for (const auto& p : positions)
    if (p.cols() != n)
      throw Error("rigidityError: frames have different vertex counts (" +
                  std::to_string(p.cols()) + " vs " + std::to_string(n) + ")");
  if (static_cast<Eigen::Index>(labels.size()) != n)
    throw Error("rigidityError: " + std::to_string(labels.size()) + " labels for " +
                std::to_string(n) + " vertices");
  if (positions.size() < 2 || n == 0) return 0.0;

  std::unordered_map<int, std::vector<Eigen::Index>> members;
  for (Eigen::Index i = 0; i < n; ++i)
    if (labels[i] >= 0) members[labels[i]].push_back(i);
  std::vector<std::vector<Eigen::Index>> parts;
  for (auto& m : members) parts.push_back(std::move(m.second));
  std::sort(parts.begin(), parts.end());  // fixed order, so the sum is reproducible
  std::vector<Eigen::Matrix3Xd> rest(parts.size());
  for (std::size_t k = 0; k < parts.size(); ++k) {
    rest[k].resize(3, static_cast<Eigen::Index>(parts[k].size()));
    for (std::size_t j = 0; j < parts[k].size(); ++j)
      rest[k].col(j) = positions[0].col(parts[k][j]);
  }

  const int frames = static_cast<int>(positions.size());
  std::vector<double> sq(frames, 0.0);
  std::size_t count_per_frame = 0;
  for (const auto& p : parts) count_per_frame += p.size();
#pragma omp parallel for schedule(dynamic)
  for (int t = 1; t < frames; ++t) {
    double s = 0.0;
    for (std::size_t k = 0; k < parts.size(); ++k) {
      Eigen::Matrix3Xd cur(3, rest[k].cols());
      for (std::size_t j = 0; j < parts[k].size(); ++j) cur.col(j) = positions[t].col(parts[k][j]);
      const RigidFit fit = kabsch(rest[k], cur);
      s += fit.rms * fit.rms * static_cast<double>(parts[k].size());
    }
    sq[t] = s;
  }
  if (count_per_frame == 0) return 0.0;
  double total = 0.0;
  for (double s : sq) total += s;
  // Frame 0 fits itself exactly; counting it would only dilute the error.
  const double rms = std::sqrt(total / (static_cast<double>(count_per_frame) * (frames - 1)));
  const Eigen::Vector3d lo = positions[0].rowwise().minCoeff();
  const Eigen::Vector3d hi = positions[0].rowwise().maxCoeff();
  const double diag = (hi - lo).norm();
  return diag > 0.0 ? rms / diag : 0.0;
}

std::vector<PartMatch> matchParts(const std::vector<std::vector<int>>& pred,
                                  const std::vector<std::vector<int>>& truth) {
  if (pred.size() != truth.size())
    throw Error("matchParts: " + std::to_string(pred.size()) + " predicted frames but " +
                std::to_string(truth.size()) + " ground-truth frames");
  Contingency table;
  for (std::size_t t = 0; t < pred.size(); ++t) {
    if (pred[t].size() != truth[t].size())
      throw Error("matchParts: frame " + std::to_string(t) + " has " +
                  std::to_string(pred[t].size()) + " predicted labels but " +
                  std::to_string(truth[t].size()) + " true labels");
    for (std::size_t i = 0; i < pred[t].size(); ++i) table.add(pred[t][i], truth[t][i]);
  }
  return table.matches();
}

std::string Report::toJson() const {
  std::ostringstream o;
  o << "{\n";
  o << "  \"pooled_ari\": " << number(pooled_ari) << ",\n";
  o << "  \"mean_frame_ari\": " << number(mean_frame_ari) << ",\n";
  o << "  \"frame_ari\": [";
  for (std::size_t i = 0; i < frame_ari.size(); ++i) o << (i ? ", " : "") << number(frame_ari[i]);
  o << "],\n";
  o << "  \"predicted_parts\": " << predicted_parts << ",\n";
  o << "  \"true_parts\": " << true_parts << ",\n";
  // null rather than -1, so that a consumer cannot average a missing value by mistake.
  o << "  \"rigidity_error\": " << (rigidity_error < 0 ? "null" : number(rigidity_error)) << ",\n";
  o << "  \"label_consistency\": " << (label_consistency < 0 ? "null" : number(label_consistency))
    << ",\n";
  o << "  \"parts\": [";
  for (std::size_t k = 0; k < parts.size(); ++k) {
    const PartMatch& m = parts[k];
    o << (k ? ",\n    " : "\n    ") << "{\"truth\": " << m.truth << ", \"points\": " << m.points
      << ", \"predicted\": " << m.predicted << ", \"recall\": " << number(m.recall)
      << ", \"precision\": " << number(m.precision) << ", \"iou\": " << number(m.iou) << "}";
  }
  o << (parts.empty() ? "],\n" : "\n  ],\n");
  o << "  \"points\": " << points << "\n";
  o << "}\n";
  return o.str();
}

Report evaluate(const std::vector<std::vector<int>>& pred,
                const std::vector<std::vector<int>>& truth,
                const std::vector<Eigen::Matrix3Xd>& positions) {
  if (pred.size() != truth.size())
    throw Error("evaluate: " + std::to_string(pred.size()) + " predicted frames but " +
                std::to_string(truth.size()) + " ground-truth frames");
  for (std::size_t t = 0; t < pred.size(); ++t)
    if (pred[t].size() != truth[t].size())
      throw Error("evaluate: frame " + std::to_string(t) + " has " +
                  std::to_string(pred[t].size()) + " predicted labels but " +
                  std::to_string(truth[t].size()) + " true labels");
  Report r;
  Contingency pooled;
  std::unordered_set<int> pred_ids, true_ids;
  r.frame_ari.resize(pred.size(), 0.0);
  for (std::size_t t = 0; t < pred.size(); ++t) {
    Contingency frame;
    for (std::size_t i = 0; i < pred[t].size(); ++i) {
      frame.add(pred[t][i], truth[t][i]);
      pooled.add(pred[t][i], truth[t][i]);
      if (pred[t][i] >= 0) pred_ids.insert(pred[t][i]);
      if (truth[t][i] >= 0) true_ids.insert(truth[t][i]);
    }
    r.frame_ari[t] = frame.ari();
  }
  r.pooled_ari = pooled.ari();
  double sum = 0.0;
  for (double a : r.frame_ari) sum += a;
  r.mean_frame_ari = pred.empty() ? 0.0 : sum / static_cast<double>(pred.size());
  r.predicted_parts = static_cast<int>(pred_ids.size());
  r.true_parts = static_cast<int>(true_ids.size());
  r.points = static_cast<std::size_t>(pooled.size());
  r.parts = pooled.matches();  // the pooled table's counts: no second pass over the labels

  if (!positions.empty()) {
    if (positions.size() != pred.size())
      throw Error("evaluate: " + std::to_string(positions.size()) + " position frames for " +
                  std::to_string(pred.size()) + " label frames");
    for (std::size_t t = 0; t < pred.size(); ++t)
      if (static_cast<std::size_t>(positions[t].cols()) != pred[t].size() ||
          pred[t].size() != pred[0].size())
        throw Error("evaluate: the rigidity error needs one vertex order; frame " +
                    std::to_string(t) + " has " + std::to_string(positions[t].cols()) +
                    " vertices and " + std::to_string(pred[t].size()) + " labels, frame 0 " +
                    std::to_string(pred[0].size()));
    r.rigidity_error = rigidityError(positions, pred[0]);
    std::size_t labelled = 0, consistent = 0;
    for (std::size_t i = 0; i < pred[0].size(); ++i) {
      bool any = false, same = true;
      for (std::size_t t = 0; t < pred.size(); ++t) {
        any = any || pred[t][i] >= 0;
        same = same && pred[t][i] == pred[0][i];
      }
      if (!any) continue;
      ++labelled;
      if (same) ++consistent;
    }
    r.label_consistency =
        labelled ? static_cast<double>(consistent) / static_cast<double>(labelled) : 1.0;
  }
  return r;
}

}  // namespace evaluation
}  // namespace pcl_animseg
