// Packs the motion method's device structures (segmentation/motion_device.h) into plain arrays for
// tracking_kernels.cu.
#include <pcl_animseg/error.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/motion_tracking.h>
#include <pcl_animseg/segmentation/task_graph.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

#include "frame_packing.h"
#include "tracking_kernels.h"

namespace pcl_animseg {
namespace gpu {

namespace {

// A sample's points (segmentation::appendPoints) and the end of its range in `begin`.
void appendSource(const Eigen::Matrix3Xd& p, const Eigen::Matrix3Xd& n, std::vector<double>& out,
                  std::vector<int>& begin) {
  if (p.cols() != n.cols())
    throw DeviceError("GPU tracking: a source has positions and normals of different counts");
  segmentation::appendPoints(p, n, out);
  begin.push_back(static_cast<int>(out.size() / 6));
}

// A batch's sources (ranges of 6-double points, source_begin) and motions (12 doubles each):
// their counts, or Error("<what>: ...") when malformed.
void countSourcesAndMotions(const std::vector<double>& points, const std::vector<int>& source_begin,
                            const std::vector<double>& motions, const std::string& what,
                            int& n_sources, int& n_motions) {
  n_sources = static_cast<int>(source_begin.size()) - 1;
  n_motions = static_cast<int>(motions.size() / detail::kPoseDoubles);
  if (n_sources < 0 || source_begin.front() != 0 ||
      static_cast<std::size_t>(source_begin.back()) * 6 != points.size() ||
      motions.size() % detail::kPoseDoubles != 0)
    throw DeviceError(what + ": the sources or motions are malformed");
}

// Error("<what>: a job out of range") unless a job's source, motion and frame are in range.
void checkJob(int source, int n_sources, int motion, int n_motions, int frame, int frames,
              const std::string& what) {
  if (source < 0 || source >= n_sources || motion < 0 || motion >= n_motions || frame < 0 ||
      frame >= frames)
    throw DeviceError(what + ": a job out of range");
}

}  // namespace

MotionTracking::MotionTracking() = default;
MotionTracking::~MotionTracking() {
  if (frames_) detail::reportCalls(*frames_, "tracking");
}

std::string MotionTracking::name() const { return deviceLabel(); }

bool MotionTracking::starting() const { return probeState() == ProbeState::Running; }

namespace detail {
void reportCalls(const FrameStore& store, const char* owner) {
  if (!std::getenv("ANIMSEG_MS_TIMING")) return;
  static const char* const kinds[FrameStore::kCallKinds] = {"residuals", "point costs", "part fits",
                                                            "rigid fits", "scored part fits"};
  for (int k = 0; k < FrameStore::kCallKinds; ++k)
    if (store.stats[k].calls)
      std::fprintf(stderr, "[gpu %s] %s: %ld calls, %ld jobs, %.3f s\n", owner, kinds[k],
                   store.stats[k].calls, store.stats[k].jobs, store.stats[k].seconds);
}

void packTree(const FlatKdTree3& tree, int node0, int point0, TrackNode* nodes, float* points) {
  const std::vector<FlatKdTree3::Node>& in = tree.nodes();
  for (std::size_t i = 0; i < in.size(); ++i) {
    const FlatKdTree3::Node& n = in[i];
    const int off = n.dim >= 0 ? node0 : point0;
    nodes[i] = TrackNode{n.split, n.dim, n.a + off, n.b + off};
  }
  const std::vector<float>& xyz = tree.leafPoints();
  for (std::size_t i = 0; i < tree.size(); ++i) {
    for (int k = 0; k < 3; ++k) points[4 * i + k] = xyz[3 * i + k];
    points[4 * i + 3] = 0.0f;
  }
}

std::vector<int> packTrees(const std::vector<const FlatKdTree3*>& trees,
                           PackedVector<TrackNode>& nodes, PackedVector<float>& points,
                           std::vector<int>& root) {
  const int n = static_cast<int>(trees.size());
  std::vector<int> node0(n + 1, 0), point0(n + 1, 0);
  for (int t = 0; t < n; ++t) {
    node0[t + 1] = node0[t] + static_cast<int>(trees[t]->nodes().size());
    point0[t + 1] = point0[t] + static_cast<int>(trees[t]->size());
  }
  nodes.resize(node0[n]);
  points.resize(4 * static_cast<std::size_t>(point0[n]));
  root.resize(n);
  // The trees side by side (packed one after the other, the motion method's 48 frames took
  // 0.07 s of a GPU run at 800k).
#pragma omp parallel for schedule(dynamic)
  for (int t = 0; t < n; ++t) {
    packTree(*trees[t], node0[t], point0[t], &nodes[node0[t]],
             &points[4 * static_cast<std::size_t>(point0[t])]);
    root[t] = trees[t]->nodes().empty() ? -1 : node0[t];
  }
  return point0;
}

FrameArrays packDeviceFrames(const segmentation::DeviceFrames& in, const std::string& what) {
  FrameArrays a;
  packDeviceFrames(in, what, a);
  return a;
}

void packDeviceFrames(const segmentation::DeviceFrames& in, const std::string& what,
                      FrameArrays& a) {
  a.spacing.clear();
  a.unoriented.clear();
  a.frames = static_cast<int>(in.frames.size());
  a.normal_cos = in.normal_cos;
  a.clip = in.clip;
  std::vector<const FlatKdTree3*> trees(in.frames.size());
  for (std::size_t t = 0; t < in.frames.size(); ++t) {
    const segmentation::DeviceFrames::Frame& f = in.frames[t];
    if (!f.tree) throw DeviceError(what + " " + std::to_string(t) + " has no tree");
    if (f.normals().size() != 3 * f.tree->size())
      throw DeviceError(what + " " + std::to_string(t) + " has one normal per point expected");
    trees[t] = f.tree;
    a.spacing.push_back(f.spacing);
    a.unoriented.push_back(f.unoriented ? 1 : 0);
  }
  // Room for these and a quarter more, where the buffers are short (the next packing, of about
  // as many points, then finds its pages; their old contents are not kept).
  std::size_t n_nodes = 0, n_points = 0;
  for (const FlatKdTree3* t : trees) n_nodes += t->nodes().size(), n_points += t->size();
  auto room = [](auto& v, std::size_t n, HostLock& lock) {
    if (v.capacity() >= n) return;
    lock.unlock();  // before the buffer is freed
    v.clear();
    v.shrink_to_fit();
    v.reserve(n + n / 4);
  };
  room(a.nodes, n_nodes, a.nodes_lock);
  room(a.points, 4 * n_points, a.points_lock);
  room(a.normals, 4 * n_points, a.normals_lock);
  const std::vector<int> point0 = packTrees(trees, a.nodes, a.points, a.root);
  a.point0 = point0;
  a.normals.resize(4 * static_cast<std::size_t>(point0.back()));
#pragma omp parallel for schedule(dynamic)
  for (int t = 0; t < a.frames; ++t) {
    const std::vector<float>& nrm = in.frames[t].normals();
    float* out = &a.normals[4 * static_cast<std::size_t>(point0[t])];
    for (std::size_t i = 0; i < nrm.size() / 3; ++i) {
      for (int k = 0; k < 3; ++k) out[4 * i + k] = nrm[3 * i + k];
      out[4 * i + 3] = 0.0f;
    }
  }
}

std::unique_ptr<FrameStore> uploadPackedFrames(const FrameArrays& packed,
                                               const FrameStore* previous) {
  auto store = std::make_unique<FrameStore>();
  uploadFrames(packed, *store);
  if (previous) std::copy(previous->stats, previous->stats + FrameStore::kCallKinds, store->stats);
  return store;
}

}  // namespace detail

void MotionTracking::setFrames(const segmentation::DeviceFrames& in) {
  // Packed now, uploaded at the first call that needs them: the CPU work between (the motion
  // method's samples and global poses, 0.1-0.2 s at 800k) overlaps the GPU's start when a probe
  // runs on another thread (pipeline.h, DeviceWarmUp).
  pending_ =
      std::make_unique<detail::FrameArrays>(detail::packDeviceFrames(in, "GPU tracking: frame"));
}

detail::FrameStore* MotionTracking::store() {
  if (pending_) {
    // Under ANIMSEG_MS_TIMING: when the first call came on the steady clock, and how long it
    // waited for the GPU's start (its "[gpu] started" line says when that ended).
    const auto t0 = std::chrono::steady_clock::now();
    requireGpu();
    if (std::getenv("ANIMSEG_MS_TIMING"))
      std::fprintf(stderr, "[gpu tracking] first call at %.3f s: waited %.3f s for the GPU\n",
                   std::chrono::duration<double>(t0.time_since_epoch()).count(),
                   std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
    const auto t1 = std::chrono::steady_clock::now();
    frames_ = detail::uploadPackedFrames(*pending_, frames_.get());
    if (std::getenv("ANIMSEG_MS_TIMING"))
      std::fprintf(stderr, "[gpu tracking] frames uploaded: %.1f MB in %.4f s\n",
                   (pending_->nodes.size() * sizeof(detail::TrackNode) +
                    (pending_->points.size() + pending_->normals.size()) * sizeof(float)) /
                       1e6,
                   std::chrono::duration<double>(std::chrono::steady_clock::now() - t1).count());
    pending_.reset();
  }
  return frames_.get();
}

std::unique_ptr<segmentation::MotionDevice> MotionTracking::fork() {
  const detail::FrameStore* own = store();
  if (!own) throw DeviceError("GPU tracking: no frames were set");
  auto f = std::make_unique<MotionTracking>();
  f->frames_ = std::make_unique<detail::FrameStore>();
  f->frames_->frames = own->frames;
  f->frames_->normal_cos = own->normal_cos;
  f->frames_->clip = own->clip;
  f->frames_->shared = own->shared ? own->shared : own;
  // Its calls come from a thread beside the caller's work (the motion method's hierarchy merges
  // beside the parts' labels, which keep every core busy): it yields its core while it waits for
  // the device. A spinning wait held a core through the merges, and the labels' parallel loops
  // waited for their thread that shared one (800k humanoid: labels 0.123-0.174 s, 0.113-0.122 s
  // yielding); asleep, each call took the wake-up longer (merges 0.06-0.07 -> 0.08-0.10 s).
  f->frames_->yield_while_waiting = true;
  f->point_parallel_limit_ = point_parallel_limit_;
  return f;
}

namespace {

// A tracking problem's arrays for the device but its tasks (levels missing: 0), checked against
// T frames; throws Error where they do not match.
detail::TrackingArrays packTracking(const segmentation::SampleTrackingProblem& problem, int T,
                                    bool with_levels) {
  const int S = problem.samples;
  const std::size_t uS = static_cast<std::size_t>(S), uT = static_cast<std::size_t>(T);
  if (S < 0 || problem.source_p.size() != uS || problem.source_n.size() != uS ||
      problem.probe_p.size() != uS || problem.probe_n.size() != uS || problem.graph.size() != uS ||
      (with_levels && problem.level.size() != uT) || problem.before.size() != uT ||
      problem.two_before.size() != uT || problem.global.size() != uT)
    throw DeviceError("GPU tracking: the problem's arrays do not match its frames and samples");
  detail::TrackingArrays a;
  a.samples = S;
  a.iterations = problem.icp_iterations;
  for (int t = 0; t < T; ++t) {
    segmentation::appendMotion(problem.global[t], a.global);
    a.before.push_back(problem.before[t]);
    a.two_before.push_back(problem.two_before[t]);
    if (!with_levels || problem.level[t].empty())
      a.level.insert(a.level.end(), uS, 0);
    else if (problem.level[t].size() != uS)
      throw DeviceError("GPU tracking: frame " + std::to_string(t) +
                        " has one level per sample expected");
    else
      a.level.insert(a.level.end(), problem.level[t].begin(), problem.level[t].end());
  }
  a.source_begin.push_back(0);
  a.probe_begin.push_back(0);
  a.adjacency_begin.push_back(0);
  for (int s = 0; s < S; ++s) {
    appendSource(problem.source_p[s], problem.source_n[s], a.source, a.source_begin);
    appendSource(problem.probe_p[s], problem.probe_n[s], a.probe, a.probe_begin);
    for (int o : problem.graph[s]) {
      if (o < 0 || o >= S) throw DeviceError("GPU tracking: a sample neighbour out of range");
      a.adjacency.push_back(o);
    }
    a.adjacency_begin.push_back(static_cast<int>(a.adjacency.size()));
  }
  return a;
}

// Flat poses and residuals (frames x samples) as the tracking's vectors.
void unpackTracking(int T, int S, const std::vector<double>& flat_poses,
                    const std::vector<double>& flat_res,
                    std::vector<std::vector<Eigen::Isometry3d>>& poses,
                    std::vector<std::vector<double>>& residual) {
  const std::size_t uT = static_cast<std::size_t>(T), uS = static_cast<std::size_t>(S);
  poses.assign(uT, std::vector<Eigen::Isometry3d>(uS, Eigen::Isometry3d::Identity()));
  residual.assign(uT, std::vector<double>(uS, 0.0));
  for (std::size_t t = 0; t < uT; ++t)
    for (std::size_t s = 0; s < uS; ++s) {
      poses[t][s] = segmentation::motionAt(&flat_poses[(t * uS + s) * detail::kPoseDoubles]);
      residual[t][s] = flat_res[t * uS + s];
    }
}

}  // namespace

void MotionTracking::trackSamples(const segmentation::SampleTrackingProblem& problem,
                                  std::vector<std::vector<Eigen::Isometry3d>>& poses,
                                  std::vector<std::vector<double>>& residual) {
  if (!store()) throw DeviceError("GPU tracking: no frames were set");
  const int T = frames_->frames, S = problem.samples;
  detail::TrackingArrays a = packTracking(problem, T, true);
  const long long TS = static_cast<long long>(T) * S;
  for (const std::vector<int>& wave : problem.waves) {
    for (int task : wave) {
      if (task < 0 || task >= TS) throw DeviceError("GPU tracking: a task out of range");
      const int before = problem.before[task / S];
      if (before < 0 || before >= T)
        throw DeviceError("GPU tracking: a task in a frame without a frame before it");
      a.tasks.push_back(task);
    }
  }
  waves_ = static_cast<int>(problem.waves.size());
  // The device takes the tasks in this order and each waits for the poses its starts read, so
  // every one of those must be a task earlier in the order (or the reference frame's): checked
  // here, where a wrong order would otherwise leave the device waiting.
  {
    std::vector<int> at(static_cast<std::size_t>(TS), -1);
    for (std::size_t k = 0; k < a.tasks.size(); ++k) {
      if (at[a.tasks[k]] >= 0) throw DeviceError("GPU tracking: a task twice");
      at[a.tasks[k]] = static_cast<int>(k);
    }
    auto ready = [&](int t, int s, int k) {
      return problem.before[t] < 0 || (at[static_cast<long long>(t) * S + s] >= 0 &&
                                       at[static_cast<long long>(t) * S + s] < k);
    };
    for (std::size_t k = 0; k < a.tasks.size(); ++k) {
      const int task = a.tasks[k], t = task / S, s = task % S, kk = static_cast<int>(k);
      if (problem.two_before[t] >= T)
        throw DeviceError("GPU tracking: a frame two before out of range");
      bool ok = ready(problem.before[t], s, kk) &&
                (problem.two_before[t] < 0 || ready(problem.two_before[t], s, kk));
      const std::vector<int>& lev = problem.level[t];
      for (int o : problem.graph[s])
        if (!lev.empty() && lev[o] < lev[s]) ok = ok && ready(t, o, kk);
      if (!ok)
        throw DeviceError(
            "GPU tracking: the waves do not put every task after the poses it starts from");
    }
  }
  std::vector<double> flat_poses, flat_res;
  device_seconds_ = detail::runTracking(*frames_, a, flat_poses, flat_res);
  if (std::getenv("ANIMSEG_MS_TIMING")) {
    std::size_t widest = 0;
    for (const std::vector<int>& wave : problem.waves) widest = std::max(widest, wave.size());
    std::fprintf(stderr, "[gpu tracking] sample poses: %d waves, %zu tasks (widest %zu), %.3f s\n",
                 waves_, a.tasks.size(), widest, device_seconds_);
  }
  unpackTracking(T, S, flat_poses, flat_res, poses, residual);
}

void MotionTracking::beginSamples(const segmentation::SampleTrackingProblem& problem) {
  if (!store()) throw DeviceError("GPU tracking: no frames were set");
  stream_.reset();
  const int T = frames_->frames;
  const detail::TrackingArrays a = packTracking(problem, T, false);
  // What frameTasks() checks the frames against, and the sample graph for the tasks' depths.
  segmentation::SampleTrackingProblem kept;
  kept.samples = problem.samples;
  kept.before = problem.before;
  kept.two_before = problem.two_before;
  kept.graph = problem.graph;
  startStreamed(std::move(kept));
  depth_.assign(static_cast<std::size_t>(T) * std::max(problem.samples, 0), 0);
  stream_ = std::make_unique<detail::TrackingStream>(*frames_, a);
  waves_ = 0;
}

void MotionTracking::trackFrames(const std::vector<int>& frames,
                                 const std::vector<Eigen::Isometry3d>& global,
                                 const std::vector<std::vector<int>>& level) {
  if (!stream_) throw DeviceError("GPU tracking: frames without beginSamples");
  if (global.size() != frames.size() || level.size() != frames.size())
    throw DeviceError("GPU tracking: one global pose and levels per frame expected");
  // The kernel's blocks take the tasks in the order given, and a block whose task still waits
  // for another holds its place: frame after frame (each by level), most of the blocks waited
  // for the slow ends of the frames before (0.14 s for the 800k humanoid's 47 frames in three
  // calls, against 0.05 s in one call in waves). So the tasks go by depth, the length of the
  // longest chain of fits that ends in them (trackSamples' waves), ties in frame and level order.
  const int S = streamed_.samples;
  std::vector<int> task_of, depth_of;  // the frames' tasks in the order below, and their depths
  std::vector<int> levels;
  std::vector<double> g;
  for (std::size_t i = 0; i < frames.size(); ++i) {
    const int t = frames[i];
    const std::vector<int> own = frameTasks(streamed_, streamed_frame_, t, level[i]);
    streamed_frame_[t] = 1;
    const int tp = streamed_.before[t], tpp = streamed_.two_before[t];
    auto depthOf = [&](int f, int s) { return depth_[static_cast<std::size_t>(f) * S + s]; };
    for (int task : own) {  // level order: a sample's neighbours of lower level come first
      const int s = task % S;
      int d = depthOf(tp, s);
      if (tpp >= 0) d = std::max(d, depthOf(tpp, s));
      for (int o : streamed_.graph[s])
        if (level[i][o] < level[i][s]) d = std::max(d, depthOf(t, o));
      depth_[static_cast<std::size_t>(task)] = d + 1;
      task_of.push_back(task);
      depth_of.push_back(d + 1);
    }
    levels.insert(levels.end(), level[i].begin(), level[i].end());
    segmentation::appendMotion(global[i], g);
  }
  // By depth (1 to the chain's length), ties in the order above.
  const int deepest = depth_of.empty() ? 0 : *std::max_element(depth_of.begin(), depth_of.end());
  std::vector<int> tasks;
  tasks.reserve(task_of.size());
  for (int k : segmentation::orderByKey(depth_of, deepest + 1)) tasks.push_back(task_of[k]);
  stream_->frames(frames, g.data(), levels.data(), tasks.data());
  waves_ += static_cast<int>(frames.empty() ? 0 : 1);
}

void MotionTracking::endSamples(std::vector<std::vector<Eigen::Isometry3d>>& poses,
                                std::vector<std::vector<double>>& residual) {
  if (!stream_) throw DeviceError("GPU tracking: endSamples without beginSamples");
  std::unique_ptr<detail::TrackingStream> stream = std::move(stream_);
  std::vector<double> flat_poses, flat_res;
  device_seconds_ = stream->end(flat_poses, flat_res);
  if (std::getenv("ANIMSEG_MS_TIMING"))
    std::fprintf(stderr,
                 "[gpu tracking] sample poses: %d kernels as the frames came, %.3f s from the "
                 "first\n",
                 waves_, device_seconds_);
  unpackTracking(frames_->frames, streamed_.samples, flat_poses, flat_res, poses, residual);
}

void MotionTracking::residuals(const segmentation::ResidualJobs& jobs, std::vector<double>& out) {
  const std::string what = "GPU residuals";
  if (!store()) throw DeviceError(what + ": no frames were set");
  int sources = 0, motions = 0;
  countSourcesAndMotions(jobs.points, jobs.source_begin, jobs.motions, what, sources, motions);
  std::vector<detail::ResidualJob> list;
  list.reserve(jobs.jobs.size());
  for (const segmentation::ResidualJobs::Job& j : jobs.jobs) {
    checkJob(j.source, sources, j.motion, motions, j.frame, frames_->frames, what);
    list.push_back({j.source, j.motion, j.frame});
  }
  const detail::CallTimer timer(*frames_, 0, list.size());
  detail::runResiduals(*frames_, jobs.points, jobs.source_begin, jobs.motions, list,
                       point_parallel_limit_, out);
}

void MotionTracking::pointCosts(const segmentation::PointCostJobs& jobs, std::vector<double>& out) {
  if (!store()) throw DeviceError("GPU point costs: no frames were set");
  const int T = frames_->frames;
  const int points = static_cast<int>(jobs.points.size() / 6);
  const std::size_t per_motion = static_cast<std::size_t>(T) * detail::kPoseDoubles;
  if (jobs.points.size() % 6 != 0 || per_motion == 0 || jobs.motions.size() % per_motion != 0 ||
      jobs.reference_frame < 0 || jobs.reference_frame >= T)
    throw DeviceError("GPU point costs: the points, motions or reference frame are malformed");
  const int motions = static_cast<int>(jobs.motions.size() / per_motion);
  std::vector<detail::PointCostJob> list;
  list.reserve(jobs.jobs.size());
  for (const segmentation::PointCostJobs::Job& j : jobs.jobs) {
    if (j.point < 0 || j.point >= points || j.motion < 0 || j.motion >= motions)
      throw DeviceError("GPU point costs: a job out of range");
    list.push_back({j.point, j.motion});
  }
  const detail::CallTimer timer(*frames_, 1, list.size());
  detail::runPointCosts(*frames_, jobs.reference_frame, jobs.per_frame, jobs.points, jobs.motions,
                        list, out);
}

bool MotionTracking::nearestMoved(const segmentation::MovedCopies& moved, std::vector<int>& pick) {
  static_assert(detail::kMovedUndecided == segmentation::kMovedUndecided,
                "the kernels' undecided pick is the interface's");
  if (!store()) throw DeviceError("GPU labels: no frames were set");
  if (!moved.fill) throw DeviceError("GPU labels: no copies to write");
  detail::runMovedNearest(*frames_, moved.order, moved.k, moved.normal_cos, moved.fill, pick);
  return true;
}

void MotionTracking::partFits(const segmentation::PartFitJobs& jobs, std::vector<double>& poses) {
  fitParts(jobs, poses, nullptr);
}

void MotionTracking::partFitsWithResiduals(const segmentation::PartFitJobs& jobs,
                                           std::vector<double>& poses,
                                           std::vector<double>& residual) {
  fitParts(jobs, poses, &residual);
}

void MotionTracking::fitParts(const segmentation::PartFitJobs& jobs, std::vector<double>& poses,
                              std::vector<double>* residual) {
  const std::string what = "GPU part fits";
  if (!store()) throw DeviceError(what + ": no frames were set");
  int sources = 0, motions = 0;
  countSourcesAndMotions(jobs.points, jobs.source_begin, jobs.motions, what, sources, motions);
  if (jobs.iterations < 0) throw DeviceError(what + ": negative iterations");
  std::vector<detail::PartFitJob> list;
  list.reserve(jobs.jobs.size());
  for (const segmentation::PartFitJobs::Job& j : jobs.jobs) {
    checkJob(j.source, sources, j.motion, motions, j.frame, frames_->frames, what);
    list.push_back({j.source, j.motion, j.frame, j.r0, j.max_dist});
  }
  const detail::CallTimer timer(*frames_, 2, list.size());
  detail::runPartFits(*frames_, jobs.points, jobs.source_begin, jobs.motions, list, jobs.iterations,
                      poses, residual);
}

void MotionTracking::scoreAndFit(const segmentation::ScoreFitJobs& jobs,
                                 std::vector<double>& scores, std::vector<int>& fitted,
                                 std::vector<double>& poses) {
  const std::string what = "GPU scored part fits";
  if (!store()) throw DeviceError(what + ": no frames were set");
  int sources = 0, motions = 0;
  countSourcesAndMotions(jobs.points, jobs.source_begin, jobs.motions, what, sources, motions);
  if (jobs.iterations < 0) throw DeviceError(what + ": negative iterations");
  if (jobs.places.size() != static_cast<std::size_t>(motions))
    throw DeviceError(what + ": a place per start is needed");
  std::vector<detail::ScoreFitJob> list;
  list.reserve(jobs.jobs.size());
  for (const segmentation::ScoreFitJobs::Job& j : jobs.jobs) {
    // More starts than a job holds: the default's two calls (residuals, then part fits).
    if (j.count > detail::kScoreFitStarts) {
      segmentation::MotionDevice::scoreAndFit(jobs, scores, fitted, poses);
      return;
    }
    if (j.count < 0 || j.first < 0 || j.first + j.count > motions)
      throw DeviceError(what + ": a job's starts out of range");
    for (int k = 0; k < j.count; ++k)
      checkJob(j.source, sources, j.first + k, motions, j.frame, frames_->frames, what);
    detail::ScoreFitJob d{};
    d.source = j.source;
    d.frame = j.frame;
    d.first = j.first;
    d.count = j.count;
    for (int k = 0; k < j.count; ++k)
      d.place[k] = jobs.places[static_cast<std::size_t>(j.first + k)];
    d.base_place = j.base_place;
    d.base_score = j.base_score;
    d.max_dist = j.max_dist;
    list.push_back(d);
  }
  const detail::CallTimer timer(*frames_, 4, list.size());
  detail::runScoreFits(*frames_, jobs.points, jobs.source_begin, jobs.motions, list,
                       static_cast<std::size_t>(motions), jobs.iterations, scores, fitted, poses);
}

}  // namespace gpu
}  // namespace pcl_animseg
