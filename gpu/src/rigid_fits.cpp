// Packs the rigid motions' fits (segmentation::RigidFitDevice) for tracking_kernels.cu.
#include <pcl_animseg/error.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/rigid_fits.h>

#include <string>

#include "frame_packing.h"
#include "tracking_kernels.h"

namespace pcl_animseg {
namespace gpu {

namespace detail {
struct RigidSources {
  DeviceArray<double> points;     // x, y, z per point, every source after the other
  std::vector<int> begin, count;  // per source, in points
};
}  // namespace detail

RigidFits::RigidFits() = default;
RigidFits::~RigidFits() {
  if (surfaces_) detail::reportCalls(*surfaces_, "rigid fits");
}

std::string RigidFits::name() const { return deviceLabel(); }

void RigidFits::setSurfaces(const segmentation::DeviceFrames& surfaces) {
  surfaces_ = detail::uploadDeviceFrames(surfaces, "GPU rigid fits: surface", surfaces_.get());
}

void RigidFits::setSources(const std::vector<const std::vector<double>*>& sources) {
  auto s = std::make_unique<detail::RigidSources>();
  std::vector<double> flat;
  for (const std::vector<double>* x : sources) {
    if (!x || x->size() % 3 != 0) throw Error("GPU rigid fits: a source is not x, y, z triples");
    s->begin.push_back(static_cast<int>(flat.size() / 3));
    s->count.push_back(static_cast<int>(x->size() / 3));
    flat.insert(flat.end(), x->begin(), x->end());
  }
  if (!flat.empty()) s->points.upload(flat);
  sources_ = std::move(s);
}

void RigidFits::fit(const std::vector<segmentation::RigidFitJob>& jobs,
                    const segmentation::RigidMotionParams& params, std::vector<double>& poses,
                    std::vector<double>& rms) {
  if (!surfaces_ || !sources_) throw Error("GPU rigid fits: no surfaces or sources were set");
  std::vector<detail::RigidJob> list;
  list.reserve(jobs.size());
  const int n_sources = static_cast<int>(sources_->begin.size());
  for (const segmentation::RigidFitJob& j : jobs) {
    if (j.source < 0 || j.source >= n_sources || j.surface < 0 || j.surface >= surfaces_->frames)
      throw Error("GPU rigid fits: a job out of range");
    detail::RigidJob r{};
    r.source_begin = sources_->begin[j.source];
    r.source_count = sources_->count[j.source];
    r.surface = j.surface;
    r.wide = j.wide ? 1 : 0;
    r.spacing = j.spacing;
    r.part_diag = j.part_diag;
    for (int k = 0; k < detail::kPoseDoubles; ++k) r.start[k] = j.start[k];
    list.push_back(r);
  }
  detail::RigidParams p{};
  p.max_iterations = params.max_iterations;
  p.max_correspondence_spacings = params.max_correspondence_spacings;
  p.coarse_distance = params.coarse_distance;
  p.transformation_epsilon = params.transformation_epsilon;
  p.relative_mse_epsilon = params.relative_mse_epsilon;
  p.max_turn = segmentation::rigidStepMaxTurn();
  const detail::CallTimer timer(*surfaces_, 3, list.size());
  detail::runRigidFits(*surfaces_, sources_->points, list, p, poses, rms);
  fits_ += static_cast<long long>(jobs.size());
  ++batches_;
}

bool RigidFits::knn(const std::vector<const FlatKdTree3*>& trees, int k,
                    const std::vector<float>& queries, const std::vector<int>& tree_of,
                    std::vector<int>& rows, std::vector<int>& count) {
  if (k < 1 || k > detail::kMaxKnn) return false;
  if (queries.size() != 3 * tree_of.size())
    throw Error("GPU k-NN: three coordinates per query expected");
  const int n_trees = static_cast<int>(trees.size());
  for (int t : tree_of)
    if (t < 0 || t >= n_trees) throw Error("GPU k-NN: a query's tree out of range");
  detail::KnnTrees packed;
  // Each tree's first node and point, then the trees packed side by side.
  std::vector<int> node0(n_trees + 1, 0), point0(n_trees + 1, 0);
  for (int t = 0; t < n_trees; ++t) {
    if (!trees[t]) throw Error("GPU k-NN: a tree is missing");
    node0[t + 1] = node0[t] + static_cast<int>(trees[t]->nodes().size());
    point0[t + 1] = point0[t] + static_cast<int>(trees[t]->size());
  }
  packed.nodes.resize(node0[n_trees]);
  packed.root.resize(n_trees);
  packed.size.resize(n_trees);
  packed.points.resize(4 * static_cast<std::size_t>(point0[n_trees]));
  packed.rows.resize(point0[n_trees]);
#pragma omp parallel for schedule(dynamic)
  for (int t = 0; t < n_trees; ++t) {
    const FlatKdTree3& tree = *trees[t];
    detail::packTree(tree, node0[t], point0[t], &packed.nodes[node0[t]],
                     &packed.points[4 * static_cast<std::size_t>(point0[t])]);
    packed.root[t] = tree.nodes().empty() ? -1 : node0[t];
    packed.size[t] = static_cast<int>(tree.size());
    std::copy(tree.leafRows().begin(), tree.leafRows().end(), packed.rows.begin() + point0[t]);
  }
  requireGpu();
  detail::runKnn(packed, k, queries, tree_of, rows, count);
  return true;
}

}  // namespace gpu
}  // namespace pcl_animseg
