// The motion method's tracking handed to a device (motion_device.h), without a GPU: what a device
// is given (waves in dependency order, the frames' trees and normals, the starts' inputs), that
// its poses are what the rest of the method uses, and that a failing device either stops the
// stage with its error or, with the fall-back on, leaves the CPU's result.
#include <gtest/gtest.h>
#include <omp.h>
#include <pcl_animseg/error.h>
#include <pcl_animseg/progress.h>
#include <pcl_animseg/segmentation/icp_step.h>
#include <pcl_animseg/segmentation/mean_shift.h>
#include <pcl_animseg/segmentation/motion_device.h>
#include <pcl_animseg/segmentation/motion_tracking.h>
#include <pcl_animseg/segmentation/task_graph.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <limits>
#include <memory>
#include <mutex>
#include <random>
#include <set>
#include <string>
#include <thread>
#include <vector>

#include "cpu_moved_nearest.h"
#include "cpu_residuals.h"
#include "synthetic_parts.h"

namespace seg = pcl_animseg::segmentation;

namespace {

// A chain of four tubes bending at three joints, sampled anew in every frame.
pcl_animseg::PointCloudSequence::Ptr chain(int frames, int points, unsigned seed) {
  return std::make_shared<pcl_animseg::PointCloudSequence>(
      animseg_test::makeTubeChain({0.8, 0.7, 0.9, 0.6}, {0.9, -1.0, 1.2}, frames, points, 0.0, seed)
          .sequence);
}

// A device on the CPU: checks what it is given, answers the tracking with poses it was handed
// (the CPU's) and computes residuals from what it was given alone (the frames' trees and leaf
// normals, the batch's sources and motions) with icp_step's arithmetic, as the GPU does; or
// throws.
class RecordingDevice : public seg::MotionDevice {
 public:
  std::string name() const override { return "recording device"; }
  bool starting() const override { return start; }
  void setFrames(const seg::DeviceFrames& f) override {
    ++frame_calls;
    threads_at_frames = omp_get_max_threads();
    frames = f;
  }
  void beginSamples(const seg::SampleTrackingProblem& p) override {
    tracker = std::this_thread::get_id();
    trackingThread() = true;
    seg::MotionDevice::beginSamples(p);
  }
  void trackFrames(const std::vector<int>& t, const std::vector<Eigen::Isometry3d>& global,
                   const std::vector<std::vector<int>>& level) override {
    EXPECT_EQ(std::this_thread::get_id(), tracker);
    frames_given += static_cast<int>(t.size());
    seg::MotionDevice::trackFrames(t, global, level);
  }
  void trackSamples(const seg::SampleTrackingProblem& p,
                    std::vector<std::vector<Eigen::Isometry3d>>& poses,
                    std::vector<std::vector<double>>& residual) override {
    ++calls;
    threads_at_tracking = omp_get_max_threads();
    start = false;  // started by its first call
    const int T = static_cast<int>(frames.frames.size()), S = p.samples;
    // Every fit once, each after the fits its starts read: the same sample in the frame before
    // (and two before) and the sample's neighbours of lower level in its own frame.
    std::vector<int> wave_of(static_cast<std::size_t>(T) * S, -1);
    int tasks = 0;
    for (std::size_t w = 0; w < p.waves.size(); ++w)
      for (int task : p.waves[w]) {
        EXPECT_EQ(wave_of[task], -1) << "task " << task << " twice";
        wave_of[task] = static_cast<int>(w);
        ++tasks;
      }
    int reference = -1;
    for (int t = 0; t < T; ++t)
      if (p.before[t] < 0) reference = t;
    EXPECT_EQ(tasks, (T - 1) * S);
    for (int t = 0; t < T; ++t) {
      const auto& f = frames.frames[t];
      ASSERT_NE(f.tree, nullptr);
      EXPECT_EQ(f.leaf_normals.size(), f.tree->leafPoints().size());
      // The normals are in the tree's leaf order: each is a unit vector of the frame's point.
      for (std::size_t i = 0; i < f.leaf_normals.size(); i += 3)
        EXPECT_NEAR(std::hypot(f.leaf_normals[i], f.leaf_normals[i + 1], f.leaf_normals[i + 2]),
                    1.0, 1e-3);
      EXPECT_GT(f.spacing, 0.0);
      if (t == reference) continue;
      for (int s = 0; s < S; ++s) {
        const int w = wave_of[t * S + s];
        ASSERT_GE(w, 0) << "frame " << t << " sample " << s << " never fitted";
        const int tp = p.before[t];
        if (tp != reference) EXPECT_LT(wave_of[tp * S + s], w);
        if (p.two_before[t] >= 0 && p.two_before[t] != reference)
          EXPECT_LT(wave_of[p.two_before[t] * S + s], w);
        for (int o : p.graph[s])
          if (p.level[t][o] < p.level[t][s]) {
            EXPECT_LT(wave_of[t * S + o], w);
          }
      }
    }
    if (fail) throw pcl_animseg::Error("recording device: out of device memory");
    poses = answer;
    residual.assign(T, std::vector<double>(S, 0.5));
  }
  // icp_step's surface error of a moved point against frame t, from the frames given.
  double surfaceError(int t, const double* y, const double* n) const {
    return animseg_test::deviceSurfaceError(frames, t, y, n);
  }
  static seg::icp_step::Rigid motionAt(const std::vector<double>& motions, std::size_t k) {
    return seg::icp_step::load(&motions[12 * k]);
  }
  void residuals(const seg::ResidualJobs& b, std::vector<double>& out) override {
    const Call call(*this);
    ++batches;
    jobs += b.jobs.size();
    out = animseg_test::cpuResiduals(frames, b);
  }
  void pointCosts(const seg::PointCostJobs& b, std::vector<double>& out) override {
    const Call call(*this);
    ++cost_batches;
    out.clear();
    const std::size_t T = frames.frames.size();
    if (b.per_frame) ++error_batches;
    for (const auto& job : b.jobs) {
      double sum = 0.0;
      for (std::size_t t = 0; t < T; ++t) {
        if (static_cast<int>(t) == b.reference_frame) {
          if (b.per_frame) out.push_back(0.0);
          continue;
        }
        const seg::icp_step::Rigid m = motionAt(b.motions, job.motion * T + t);
        double y[3], n[3];
        seg::icp_step::apply(m, &b.points[6 * job.point], y);
        seg::icp_step::rotate(m, &b.points[6 * job.point + 3], n);
        const double e = surfaceError(static_cast<int>(t), y, n);
        if (b.per_frame) out.push_back(e);
        sum += e;
      }
      if (!b.per_frame) out.push_back(sum);
    }
  }
  // The motion method's part fit from what it was given (cpuPartFits: icp_step's damped ICP,
  // kept when its residual is at most r0).
  void partFits(const seg::PartFitJobs& b, std::vector<double>& poses) override {
    const Call call(*this);
    ++fit_batches;
    fits += b.jobs.size();
    poses = animseg_test::cpuPartFits(frames, b);
  }
  // Scored part fits: MotionDevice's default (a residual batch, then a part-fit batch), counted
  // as one call; the batches it makes are counted apart (inner_*).
  void scoreAndFit(const seg::ScoreFitJobs& jobs, std::vector<double>& scores,
                   std::vector<int>& fitted, std::vector<double>& poses) override {
    ++score_fit_calls;
    const int b0 = batches, f0 = fit_batches;
    seg::MotionDevice::scoreAndFit(jobs, scores, fitted, poses);
    inner_batches += batches - b0;
    inner_fit_batches += fit_batches - f0;
  }
  int score_fit_calls = 0, inner_batches = 0, inner_fit_batches = 0;
  // Every frame's labels by the moved reference, as specified (cpu_moved_nearest.h), from the
  // frames given; or none (offer_moved false), or every point left undecided (undecide_all).
  bool nearestMoved(const seg::MovedCopies& m, std::vector<int>& pick) override {
    const Call call(*this);
    ++moved_calls;
    if (!offer_moved) return false;
    pick = animseg_test::movedNearestBySpec(frames, m);
    if (undecide_all) std::fill(pick.begin(), pick.end(), seg::kMovedUndecided);
    return true;
  }
  bool offer_moved = true, undecide_all = false;
  int moved_calls = 0;
  // Which threads made the batch calls, and whether two calls were ever in the device at once.
  struct Call {
    explicit Call(RecordingDevice& d) : device(d) {
      if (device.inside.fetch_add(1) != 0) device.overlapped = true;
      const std::thread::id me = std::this_thread::get_id();
      if (me == device.home && device.home_threads < 0) device.home_threads = omp_get_max_threads();
      // (A thread's id may be reused by a later thread: the tracker is told by a flag of its own.)
      const bool beside = me != device.home && !trackingThread();
      (trackingThread() ? device.tracker_calls
       : beside         ? device.beside_calls
                        : device.home_calls)++;
      if (device.fail_off_thread && beside) {
        device.inside.fetch_sub(1);
        throw pcl_animseg::Error("recording device: kernel fault beside the part labels");
      }
    }
    ~Call() { device.inside.fetch_sub(1); }
    RecordingDevice& device;
  };
  // Calls from any thread but `home` and the samples' tracker fail (the hierarchy's merges run on
  // a thread of their own).
  bool fail_off_thread = false;
  std::thread::id home = std::this_thread::get_id();
  // Whether this thread gave the samples' frames (beginSamples .. endSamples, beside the chain of
  // global poses).
  static bool& trackingThread() {
    thread_local bool tracking = false;
    return tracking;
  }
  std::thread::id tracker;
  int home_threads = -1;  // the caller's thread count at its first call
  std::atomic<int> home_calls{0}, tracker_calls{0}, beside_calls{0};
  std::atomic<int> inside{0};
  std::atomic<bool> overlapped{false};
  int fit_batches = 0;
  std::size_t fits = 0;
  int calls = 0, frame_calls = 0, batches = 0, cost_batches = 0, error_batches = 0;
  std::size_t jobs = 0;
  bool fail = false;
  bool start = false;  // starting() until the first call
  int threads_at_frames = 0, threads_at_tracking = 0, frames_given = 0;
  seg::DeviceFrames frames;
  std::vector<std::vector<Eigen::Isometry3d>> answer;
};

// Lends a RecordingDevice to MeanShiftSegmentation.
class RecordingBackend : public seg::MeanShiftDeviceBackend {
 public:
  std::string name() const override { return "recording backend"; }
  void seekModes(const Eigen::MatrixXf&, const Eigen::RowVectorXf&, const Eigen::RowVectorXf&,
                 const std::vector<char>&, const seg::MeanShiftParams&, Eigen::MatrixXf&,
                 Eigen::VectorXf&) override {
    throw pcl_animseg::Error("not used");
  }
  void density(const Eigen::MatrixXf&, const Eigen::RowVectorXf&, const Eigen::RowVectorXf&,
               const std::vector<char>&, const seg::MeanShiftParams&, const Eigen::MatrixXf&,
               const std::vector<char>&, Eigen::VectorXf&) override {
    throw pcl_animseg::Error("not used");
  }
  seg::MotionDevice* motionDevice() override { return &device; }
  RecordingDevice device;
};

// The motion method as the pipeline runs it (no densities: a device backend only fits and
// scores), on the CPU or with `backend`.
seg::MeanShiftParams motionParams() {
  seg::MeanShiftParams params;
  params.method = seg::MeanShiftMethod::Motion;
  params.record_densities = false;
  return params;
}

seg::SegmentationResult segmentOnCpu(const pcl_animseg::PointCloudSequence::Ptr& seq) {
  seg::MeanShiftSegmentation cpu;
  cpu.setInputSequence(seq);
  cpu.setParams(motionParams());
  seg::SegmentationResult result;
  cpu.segment(result);
  EXPECT_EQ(cpu.deviceUsed(), "cpu");
  return result;
}

// The CPU's samples' poses, which a RecordingDevice answers the tracking with.
std::vector<std::vector<Eigen::Isometry3d>> cpuPoses(const pcl_animseg::PointCloudSequence& seq) {
  seg::MotionTrackingParams mp;
  mp.point_neighbours = motionParams().neighbours;
  return seg::trackSamples(seq, mp).poses;
}

// The motion method with `backend`'s device; `used`, where given, gets the device it ran on.
seg::SegmentationResult segmentWith(const pcl_animseg::PointCloudSequence::Ptr& seq,
                                    const std::shared_ptr<RecordingBackend>& backend,
                                    std::string* used = nullptr) {
  seg::MeanShiftSegmentation dev;
  dev.setInputSequence(seq);
  dev.setParams(motionParams());
  dev.setDeviceBackend(backend);
  seg::SegmentationResult got;
  dev.segment(got);
  if (used) *used = dev.deviceUsed();
  return got;
}

}  // namespace

TEST(MotionDevice, WavesRunEachFitAfterTheFitsItsStartsRead) {
  const auto seq = chain(7, 3000, 3);
  seg::MotionTrackingParams params;
  params.reference_frame = 3;  // frames on both sides: two chains away from the reference
  const seg::SampleTracks cpu = seg::trackSamples(*seq, params);
  RecordingDevice device;
  device.answer = cpu.poses;
  params.device = &device;
  const seg::SampleTracks dev = seg::trackSamples(*seq, params);
  EXPECT_EQ(device.calls, 1);
  EXPECT_EQ(device.frames_given, 6);  // every frame but the reference, as the chain found it
  // The device's poses are the tracks' poses and positions.
  ASSERT_EQ(dev.poses.size(), cpu.poses.size());
  for (std::size_t t = 0; t < cpu.poses.size(); ++t) {
    for (std::size_t s = 0; s < cpu.poses[t].size(); ++s)
      EXPECT_TRUE(dev.poses[t][s].isApprox(cpu.poses[t][s], 0.0)) << t << " " << s;
    EXPECT_EQ((dev.positions[t] - cpu.positions[t]).norm(), 0.0);
    if (static_cast<int>(t) != params.reference_frame) EXPECT_DOUBLE_EQ(dev.residual[t], 0.5);
  }
}

TEST(MotionDevice, ADeviceThatComputesAsTheCpuGivesTheCpusLabels) {
  const auto seq = chain(8, 3000, 4);
  const seg::SegmentationResult expected = segmentOnCpu(seq);

  auto backend = std::make_shared<RecordingBackend>();
  backend->device.answer = cpuPoses(*seq);
  std::string used;
  const seg::SegmentationResult got = segmentWith(seq, backend, &used);
  EXPECT_EQ(backend->device.calls, 1);
  EXPECT_EQ(backend->device.frame_calls, 1);
  EXPECT_GT(backend->device.batches, 1);  // the edges, then the merges' batches
  // Phase 1 merges the samples' groups into a few dozen (here 421 merges of 435 samples), one
  // batch each when made one at a time; prepared ahead, several in a batch (181 batches), and
  // every batch of the run together stays well below one per merge.
  EXPECT_LT(backend->device.batches, static_cast<int>(backend->device.answer[0].size() * 3 / 4));
  EXPECT_GT(backend->device.jobs, 1000u);
  EXPECT_GT(backend->device.cost_batches, 0);  // the border rounds and the final borders
  EXPECT_GT(backend->device.error_batches, 0);  // the dissolve costs' errors per frame
  EXPECT_GT(backend->device.fit_batches, 0);   // the part fits, frame positions side by side
  EXPECT_GT(backend->device.fits, 100u);
  EXPECT_EQ(backend->device.moved_calls, 1);  // every frame's labels
  EXPECT_EQ(used, "recording backend");
  EXPECT_EQ(got.num_clusters, expected.num_clusters);
  EXPECT_EQ(animseg_test::pooled(got.labels), animseg_test::pooled(expected.labels));
  // The merges the device's run evaluated ahead, in batches, are the CPU's one at a time.
  EXPECT_EQ(got.merges, expected.merges);
  // The samples' frames were given one by one, from a thread beside the chain of global poses;
  // the hierarchy's merges above the parts ran beside the parts' motions and labels, on a thread
  // of their own; and the three threads' calls took turns.
  EXPECT_EQ(backend->device.frames_given, static_cast<int>(seq->size()) - 1);
  EXPECT_NE(backend->device.tracker, backend->device.home);
  EXPECT_GT(backend->device.tracker_calls, 0);  // the frames' levels
  EXPECT_GT(backend->device.beside_calls, 0);   // the hierarchy's merges
  EXPECT_GT(backend->device.home_calls, 0);
  EXPECT_FALSE(backend->device.overlapped);
}

// The motion method on an 8-frame chain with a recording device, once with a setting off and once
// on (`set(params, on)`): the CPU's parts, labels and merges both ways; `count(device)` after
// each run, returned as {off, on}.
template <class Set, class Count>
std::pair<int, int> cpusMergesBothWays(Set set, Count count) {
  const auto seq = chain(8, 3000, 4);
  seg::MotionTrackingParams mp;
  mp.point_neighbours = motionParams().neighbours;
  std::vector<int> cpu_flat;
  int cpu_parts = 0;
  std::vector<seg::ClusterMerge> cpu_merges;
  seg::segmentByTracking(*seq, mp, cpu_flat, cpu_parts, cpu_merges);
  const auto answer = cpuPoses(*seq);
  int counted[2] = {0, 0};
  for (int on = 0; on < 2; ++on) {
    RecordingDevice device;
    device.answer = answer;
    seg::MotionTrackingParams dp = mp;
    dp.device = &device;
    set(dp, on == 1);
    std::vector<int> flat;
    int parts = 0;
    std::vector<seg::ClusterMerge> merges;
    seg::segmentByTracking(*seq, dp, flat, parts, merges);
    EXPECT_EQ(parts, cpu_parts) << on;
    EXPECT_EQ(flat, cpu_flat) << on;
    EXPECT_EQ(merges, cpu_merges) << on;
    counted[on] = count(device);
  }
  return {counted[0], counted[1]};
}

// The part merges' speculative fits (MotionTrackingParams::speculate_merge_fits): with them the
// CPU's merges, in fewer part-fit batches.
TEST(MotionDevice, SpeculativeMergeFitsSaveBatchesAndKeepTheCpusMerges) {
  const auto [without, with] =
      cpusMergesBothWays([](seg::MotionTrackingParams& p, bool on) { p.speculate_merge_fits = on; },
                         [](const RecordingDevice& d) { return d.fit_batches; });
  EXPECT_GT(without, 0);
  EXPECT_LT(with, without);
}

// The part fits' score batches and the fits they decide in one call each
// (MotionTrackingParams::fuse_score_fits): the CPU's labels and merges either way, in fewer calls
// with it.
TEST(MotionDevice, ScoredPartFitsInOneCallKeepTheCpusMergesInFewerCalls) {
  // Round trips: the residual and part-fit batches made directly, and the scored part fits.
  auto calls = [](const RecordingDevice& d) {
    return d.batches - d.inner_batches + d.fit_batches - d.inner_fit_batches + d.score_fit_calls;
  };
  std::vector<int> fused;  // the scored part fits' calls, off then on
  const auto [without, with] =
      cpusMergesBothWays([](seg::MotionTrackingParams& p, bool on) { p.fuse_score_fits = on; },
                         [&](const RecordingDevice& d) {
                           fused.push_back(d.score_fit_calls);
                           return calls(d);
                         });
  ASSERT_EQ(fused.size(), 2u);
  EXPECT_EQ(fused[0], 0);
  EXPECT_GT(fused[1], 0);
  EXPECT_LT(with, without);
  std::printf(
      "the motion method's device calls: %d, with scored part fits in one call %d (%d "
      "of them)\n",
      without, with, fused[1]);
}

// Every frame's labels by the moved reference: from a device that leaves every point undecided
// (the cores search them all again) or one that does not offer the search, the CPU's labels.
TEST(MotionDevice, EveryFramesLabelsFromADeviceThatLeavesThemOrDoesNotOfferThemAreTheCpus) {
  const auto seq = chain(5, 2500, 9);
  const seg::SegmentationResult expected = segmentOnCpu(seq);
  const auto answer = cpuPoses(*seq);
  for (int offer = 0; offer < 2; ++offer) {
    auto backend = std::make_shared<RecordingBackend>();
    backend->device.answer = answer;
    backend->device.offer_moved = offer == 1;
    backend->device.undecide_all = true;
    const seg::SegmentationResult got = segmentWith(seq, backend);
    EXPECT_EQ(backend->device.moved_calls, 1) << offer;
    EXPECT_EQ(animseg_test::pooled(got.labels), animseg_test::pooled(expected.labels)) << offer;
  }
}

// The search as specified (the device's contract) gives the cores' picks wherever it decides,
// with ties of every kind planted (makeMovedCase), and leaves undecided only picks that a tie at
// the k-th nearest decides.
TEST(MovedNearest, TheContractIsTheCoresSearchWhereItDecides) {
  const auto seq = chain(4, 3000, 5);
  animseg_test::MovedCase c;
  animseg_test::makeMovedCase(*seq, c);
  const std::vector<int> spec = animseg_test::movedNearestBySpec(c.frames, c.copies);
  const std::vector<int> tree = animseg_test::movedNearestByTree(c.frames, c.copies);
  ASSERT_EQ(spec.size(), tree.size());
  ASSERT_EQ(spec.size(), seq->totalPoints());
  std::size_t undecided = 0, differ = 0, duplicates = 0;
  for (std::size_t i = 0; i < spec.size(); ++i) {
    if (spec[i] == seg::kMovedUndecided) {
      ++undecided;
      continue;
    }
    differ += spec[i] != tree[i];
    EXPECT_GE(spec[i], 0);
    // A pick of the lower of two copies at the same place (every 97th is the next one's twin).
    const auto at = std::find(c.copies.order.begin(), c.copies.order.end(), spec[i]);
    duplicates += (at - c.copies.order.begin()) % 97 == 0;
  }
  EXPECT_EQ(differ, 0u);
  // Around the ten copies at one place, in the frames whose normals are oriented (25 of 12 000
  // points), and nowhere else.
  EXPECT_GT(undecided, 0u);
  EXPECT_LT(undecided, 100u);
  EXPECT_GT(duplicates, 0u);
}

// A device that fails in the hierarchy's merges, which run on a thread of their own beside the
// part motions and labels: the stage stops with the device's error (no crash, no wait), or
// with the fall-back on gives the CPU's labels and merges.
TEST(MotionDevice, AFailureBesideThePartLabelsStopsTheStageOrFallsBack) {
  const auto seq = chain(6, 2500, 7);
  const seg::SegmentationResult expected = segmentOnCpu(seq);
  const auto answer = cpuPoses(*seq);
  for (const bool fallback : {false, true}) {
    auto backend = std::make_shared<RecordingBackend>();
    backend->device.answer = answer;
    backend->device.fail_off_thread = true;
    seg::MeanShiftSegmentation ms;
    ms.setInputSequence(seq);
    ms.setParams(motionParams());
    ms.setDeviceBackend(backend, fallback);
    seg::SegmentationResult got;
    if (!fallback) {
      try {
        ms.segment(got);
        ADD_FAILURE() << "a device failing beside the part labels must stop the stage";
      } catch (const pcl_animseg::Error& e) {
        EXPECT_NE(std::string(e.what()).find("beside the part labels"), std::string::npos)
            << e.what();
      }
    } else {
      ms.segment(got);
      EXPECT_EQ(ms.deviceUsed(), "cpu");
      EXPECT_NE(ms.fallbackReason().find("beside the part labels"), std::string::npos);
      EXPECT_EQ(animseg_test::pooled(got.labels), animseg_test::pooled(expected.labels));
      EXPECT_EQ(got.merges, expected.merges);
    }
    // It did run on a thread of its own (beside the caller's and the samples' tracking's).
    EXPECT_GT(backend->device.beside_calls, 0);
  }
}

TEST(MotionDevice, ADeviceStillStartingIsLeftACoreUntilItsFirstCall) {
  const int threads = omp_get_max_threads();
  omp_set_num_threads(4);
  const auto seq = chain(6, 2500, 6);
  const seg::SegmentationResult expected = segmentOnCpu(seq);
  auto backend = std::make_shared<RecordingBackend>();
  backend->device.answer = cpuPoses(*seq);
  backend->device.start = true;
  const seg::SegmentationResult got = segmentWith(seq, backend);
  // The CPU work before the first call ran on one thread fewer (as did the chain of global poses
  // beside the samples' tracking); the caller's calls after it, on every thread.
  EXPECT_EQ(backend->device.threads_at_frames, 3);
  EXPECT_EQ(backend->device.home_threads, 4);
  EXPECT_EQ(omp_get_max_threads(), 4);
  // The thread count does not change the result.
  EXPECT_EQ(got.num_clusters, expected.num_clusters);
  EXPECT_EQ(animseg_test::pooled(got.labels), animseg_test::pooled(expected.labels));
  EXPECT_EQ(got.merges, expected.merges);
  omp_set_num_threads(threads);
}

TEST(MotionDevice, AFailingDeviceStopsTheStageOrFallsBackToTheCpu) {
  const auto seq = chain(6, 2500, 5);
  const seg::MeanShiftParams params = motionParams();
  const seg::SegmentationResult expected = segmentOnCpu(seq);

  auto backend = std::make_shared<RecordingBackend>();
  backend->device.fail = true;
  seg::MeanShiftSegmentation strict;
  strict.setInputSequence(seq);
  strict.setParams(params);
  strict.setDeviceBackend(backend, /*cpu_fallback=*/false);
  seg::SegmentationResult none;
  try {
    strict.segment(none);
    ADD_FAILURE() << "a failing device must stop the stage";
  } catch (const pcl_animseg::Error& e) {
    EXPECT_NE(std::string(e.what()).find("out of device memory"), std::string::npos);
  }

  seg::MeanShiftSegmentation lenient;
  lenient.setInputSequence(seq);
  lenient.setParams(params);
  lenient.setDeviceBackend(backend, /*cpu_fallback=*/true);
  // The failed try's progress stages (the tracking's, begun before the device failed) are
  // closed: the CPU's run is recorded under the caller's stage, and that stage ends as itself.
  pcl_animseg::Progress progress(true, false);
  lenient.setProgress(&progress);
  progress.begin("mean_shift");
  seg::SegmentationResult got;
  lenient.segment(got);
  EXPECT_EQ(progress.depth(), 1u);
  progress.end();
  EXPECT_EQ(lenient.deviceUsed(), "cpu");
  EXPECT_NE(lenient.fallbackReason().find("out of device memory"), std::string::npos);
  EXPECT_EQ(animseg_test::pooled(got.labels), animseg_test::pooled(expected.labels));
  std::vector<std::string> names;
  for (const auto& t : progress.timings()) names.push_back(t.first);
  EXPECT_NE(std::find(names.begin(), names.end(), "mean_shift"), names.end());
  EXPECT_NE(std::find(names.begin(), names.end(), "mean_shift/tracking samples"), names.end());
  for (const auto& n : names) EXPECT_EQ(n.find("tracking samples/"), std::string::npos) << n;
}

TEST(TaskWaves, EachTaskInTheWaveAfterItsLongestChain) {
  // 0 -> 1 -> 3, 0 -> 2, 2 -> 3, 4 alone; 3 waits for its longest chain (0, 1 or 0, 2).
  const std::vector<std::vector<int>> succ{{1, 2}, {3}, {3}, {}, {}};
  const auto waves = seg::taskWaves(succ);
  ASSERT_EQ(waves.size(), 3u);
  EXPECT_EQ(waves[0], (std::vector<int>{0, 4}));
  EXPECT_EQ(waves[1], (std::vector<int>{1, 2}));
  EXPECT_EQ(waves[2], (std::vector<int>{3}));
  EXPECT_THROW(seg::taskWaves({{1}, {0}}), pcl_animseg::Error);
  EXPECT_THROW(seg::taskWaves({{5}}), pcl_animseg::Error);
  EXPECT_TRUE(seg::taskWaves({}).empty());
}

// Farthest-point sampling on any number of threads picks what one scan in point order picks (the
// first point of the largest distance), with exact ties (coincident points, a grid), skipped
// points, and more samples asked for than the cloud has distinct points.
TEST(MotionTracking, FarthestPointSamplesAreTheSameOnAnyNumberOfThreads) {
  using Cloud = pcl_animseg::PointCloudSequence::Cloud;
  auto reference = [](const Cloud& cloud, int count, unsigned seed,
                      const std::vector<char>& skip) {
    const int n = static_cast<int>(cloud.size());
    std::vector<int> out;
    int start = static_cast<int>((1103515245u * seed + 12345u) % static_cast<unsigned>(n));
    const bool skipping = skip.size() == cloud.size();
    for (int k = 0; skipping && skip[start] && k < n; ++k) start = (start + 1) % n;
    if (skipping && skip[start]) return out;
    out.push_back(start);
    std::vector<double> dmin(n, std::numeric_limits<double>::max());
    for (int i = 0; skipping && i < n; ++i)
      if (skip[i]) dmin[i] = -1.0;
    while (static_cast<int>(out.size()) < count) {
      const Eigen::Vector3d s = cloud[out.back()].getVector3fMap().cast<double>();
      int far = 0;
      for (int i = 0; i < n; ++i) {
        dmin[i] = std::min(dmin[i], (cloud[i].getVector3fMap().cast<double>() - s).squaredNorm());
        if (dmin[i] > dmin[far]) far = i;
      }
      if (dmin[far] <= 0.0) break;
      out.push_back(far);
    }
    return out;
  };
  // A 20 x 20 x 8 grid (many equal distances), each point twice, shuffled deterministically.
  Cloud cloud;
  for (int z = 0; z < 8; ++z)
    for (int y = 0; y < 20; ++y)
      for (int x = 0; x < 20; ++x) {
        pcl::PointNormal q;
        q.x = 0.1f * x, q.y = 0.1f * y, q.z = 0.1f * z;
        q.normal_x = q.normal_y = 0.0f, q.normal_z = 1.0f;
        cloud.push_back(q);
        cloud.push_back(q);
      }
  for (std::size_t i = cloud.size() - 1, r = 12345; i > 0; --i) {
    r = (r * 6364136223846793005ull + 1442695040888963407ull);
    std::swap(cloud[i], cloud[(r >> 33) % (i + 1)]);
  }
  std::vector<char> skip(cloud.size(), 0);
  for (std::size_t i = 0; i < skip.size(); i += 7) skip[i] = 1;
  const int threads = omp_get_max_threads();
  for (const auto& sk : {std::vector<char>(), skip})
    for (int count : {1, 300, 8000}) {
      const std::vector<int> want = reference(cloud, count, 3, sk);
      if (count < 3200) {
        EXPECT_EQ(want.size(), static_cast<std::size_t>(count));
      }
      if (sk.empty() && count == 8000) {
        EXPECT_EQ(want.size(), 3200u);  // the distinct points
      }
      for (int t : {1, 2, 3, 5}) {
        omp_set_num_threads(t);
        EXPECT_EQ(seg::farthestPointSamples(cloud, count, 3, sk), want)
            << count << " samples on " << t << " threads" << (sk.empty() ? "" : ", skipping");
      }
      omp_set_num_threads(threads);
    }
}

// The final borders' alpha expansions with the expansions of far apart labels side by side give
// the labels of the expansions one after the other, on any number of threads: a grid of 14
// stripes whose points near a border may take the labels within 3 steps, with costs that move
// some of them. Stripes 6 wide hold labels that no point may both take but that meet over an
// edge: their expansions read each other's points too.
TEST(MotionTracking, AlphaExpansionsSideBySideGiveTheSerialLabels) {
  constexpr int W = 70, H = 24, kHops = 3;
  const int n = W * H;
  unsigned long long r = 2024;
  auto uniform = [&r] {
    r = r * 6364136223846793005ull + 1442695040888963407ull;
    return static_cast<double>(r >> 11) / 9007199254740992.0;
  };
  const int widths[] = {3, 6, 2, 6, 4, 7, 6, 5, 2, 6, 3, 6, 8, 6};
  constexpr int K = static_cast<int>(sizeof(widths) / sizeof(widths[0]));
  // Labels in another order than the stripes, so that labels in a row lie apart.
  const int label_of[K] = {0, 7, 1, 8, 2, 9, 3, 10, 4, 11, 5, 12, 6, 13};
  std::vector<int> stripe_of(W);
  for (int k = 0, x = 0; k < K; ++k)
    for (int w = 0; w < widths[k] && x < W; ++w) stripe_of[x++] = label_of[k];
  std::vector<int> start(n);
  for (int y = 0; y < H; ++y)
    for (int x = 0; x < W; ++x) start[y * W + x] = stripe_of[x];
  std::vector<std::vector<int>> nbr(n);
  std::vector<std::vector<std::pair<int, double>>> edges(n);
  for (int y = 0; y < H; ++y)
    for (int x = 0; x < W; ++x) {
      const int i = y * W + x;
      if (x + 1 < W) nbr[i].push_back(i + 1), nbr[i + 1].push_back(i);
      if (y + 1 < H) nbr[i].push_back(i + W), nbr[i + W].push_back(i);
      if (x + 1 < W) edges[i].push_back({i + 1, 0.2 + uniform()});
      if (y + 1 < H) edges[i].push_back({i + W, 0.2 + uniform()});
    }
  std::vector<std::vector<int>> cand(n);
  for (int i = 0; i < n; ++i) cand[i] = {start[i]};
  for (int h = 0; h < kHops; ++h) {
    std::vector<std::vector<int>> next(cand);
    for (int i = 0; i < n; ++i) {
      for (int j : nbr[i]) next[i].insert(next[i].end(), cand[j].begin(), cand[j].end());
      std::sort(next[i].begin(), next[i].end());
      next[i].erase(std::unique(next[i].begin(), next[i].end()), next[i].end());
    }
    cand.swap(next);
  }
  std::vector<std::vector<double>> unary(n);
  for (int i = 0; i < n; ++i)
    for (int l : cand[i]) unary[i].push_back(4.0 * uniform() + (l == start[i] ? 0.0 : 1.0));

  // The longest chain of expansions that must wait for each other, from the sets each reads
  // (the points that may take its label and their edges' other ends) and writes (the former).
  std::vector<int> present;
  for (int i = 0; i < n; ++i)
    if (cand[i].size() >= 2) present.insert(present.end(), cand[i].begin(), cand[i].end());
  std::sort(present.begin(), present.end());
  present.erase(std::unique(present.begin(), present.end()), present.end());
  const int nl = static_cast<int>(present.size());
  std::vector<std::set<int>> writes(nl), reads(nl);
  for (int a = 0; a < nl; ++a)
    for (int i = 0; i < n; ++i)
      if (cand[i].size() >= 2 && std::binary_search(cand[i].begin(), cand[i].end(), present[a])) {
        writes[a].insert(i);
        reads[a].insert(i);
        for (int j : nbr[i]) reads[a].insert(j);
      }
  auto meets = [](const std::set<int>& x, const std::set<int>& y) {
    for (int i : x)
      if (y.count(i)) return true;
    return false;
  };
  std::vector<int> depth(nl, 1);
  int expected_chain = 0;
  for (int a = 0; a < nl; ++a) {
    for (int b = 0; b < a; ++b)
      if (meets(writes[a], reads[b]) || meets(writes[b], reads[a]))
        depth[a] = std::max(depth[a], depth[b] + 1);
    expected_chain = std::max(expected_chain, depth[a]);
  }

  std::vector<int> serial = start;
  const int serial_chain = seg::detail::alphaExpansions(cand, unary, edges, serial, false);
  EXPECT_EQ(serial_chain, expected_chain);
  int moved = 0;
  for (int i = 0; i < n; ++i) moved += serial[i] != start[i];
  EXPECT_GT(moved, 50);  // the expansions do move borders
  EXPECT_LT(moved, n / 2);
  EXPECT_GE(serial_chain, 2);
  EXPECT_LT(serial_chain, K);  // some labels' expansions are independent
  const int threads = omp_get_max_threads();
  for (int t : {1, 2, 3, 5}) {
    omp_set_num_threads(t);
    std::vector<int> label = start;
    EXPECT_EQ(seg::detail::alphaExpansions(cand, unary, edges, label, true), serial_chain);
    EXPECT_EQ(label, serial) << t << " threads";
  }
  omp_set_num_threads(threads);
  std::vector<int> bad = start;
  bad.pop_back();
  EXPECT_THROW(seg::detail::alphaExpansions(cand, unary, edges, bad, true), pcl_animseg::Error);
  std::vector<int> label = start;
  auto backwards = edges;
  backwards[5].push_back({4, 1.0});
  EXPECT_THROW(seg::detail::alphaExpansions(cand, unary, backwards, label, true),
               pcl_animseg::Error);
  auto short_unary = unary;
  for (auto& u : short_unary)
    if (u.size() >= 2) {
      u.pop_back();
      break;
    }
  EXPECT_THROW(seg::detail::alphaExpansions(cand, short_unary, edges, label, true),
               pcl_animseg::Error);
  EXPECT_EQ(label, start);  // nothing moved by a call that threw
}

// Frames given as they come (beginSamples .. endSamples): each after the frames it starts from,
// once, with a level per sample; anything else is an error, not a wait or a wrong pose.
TEST(MotionDevice, FramesGivenOutOfOrderAreAnError) {
  const auto seq = chain(4, 2000, 3);
  seg::MotionTrackingParams params;
  const int S = static_cast<int>(seg::trackSamples(*seq, params).sample_points.size());
  RecordingDevice device;
  seg::SampleTrackingProblem p;
  p.samples = S;
  p.graph.assign(S, {});
  p.before = {-1, 0, 1, 2};
  p.two_before = {-1, -1, 0, 1};
  p.global.assign(4, Eigen::Isometry3d::Identity());
  const std::vector<int> flat(S, 0);
  const Eigen::Isometry3d I = Eigen::Isometry3d::Identity();
  device.beginSamples(p);
  EXPECT_THROW(device.trackFrames({2}, {I}, {flat}), pcl_animseg::Error);  // before frame 1
  EXPECT_THROW(device.trackFrames({0}, {I}, {flat}), pcl_animseg::Error);  // the reference
  EXPECT_THROW(device.trackFrames({4}, {I}, {flat}), pcl_animseg::Error);  // no such frame
  EXPECT_THROW(device.trackFrames({1}, {I}, {std::vector<int>(S - 1, 0)}), pcl_animseg::Error);
  EXPECT_THROW(device.trackFrames({1}, {}, {flat}), pcl_animseg::Error);
  EXPECT_NO_THROW(device.trackFrames({1, 2}, {I, I}, {flat, flat}));
  EXPECT_THROW(device.trackFrames({2}, {I}, {flat}), pcl_animseg::Error);  // twice
  EXPECT_NO_THROW(device.trackFrames({3}, {I}, {flat}));
}

// frameTasks: a frame's tasks by level, ties in sample order (what the devices' kernels take in
// turn), also where a level is out of the BFS's range (a sample left unreached: -1).
struct TaskOrder : RecordingDevice {
  using seg::MotionDevice::frameTasks;
};
TEST(MotionDevice, AFramesTasksGoByLevelThenBySample) {
  const int S = 500;
  seg::SampleTrackingProblem p;
  p.samples = S;
  p.before = {-1, 0, 1};
  p.two_before = {-1, -1, 0};
  const std::vector<char> given{1, 1, 0};  // the reference and frame 1: frame 2 may come
  std::mt19937 rng(7);
  auto byLevelThenSample = [&](const std::vector<int>& level) {
    std::vector<int> order(S);
    for (int s = 0; s < S; ++s) order[s] = s;
    std::sort(order.begin(), order.end(),
              [&](int a, int b) { return level[a] != level[b] ? level[a] < level[b] : a < b; });
    for (int& s : order) s += 2 * S;
    return order;
  };
  for (int maxlevel : {0, 6, S - 1}) {
    std::uniform_int_distribution<int> pick(0, maxlevel);
    std::vector<int> level(S);
    for (int& l : level) l = pick(rng);
    EXPECT_EQ(TaskOrder::frameTasks(p, given, 2, level), byLevelThenSample(level)) << maxlevel;
  }
  std::vector<int> level(S);
  for (int s = 0; s < S; ++s) level[s] = (s * 7) % 5 - 1;  // -1 .. 3: some unreached
  const std::vector<int> tasks = TaskOrder::frameTasks(p, given, 2, level);
  EXPECT_EQ(tasks, byLevelThenSample(level));
  EXPECT_EQ(level[tasks.front() - 2 * S], -1);
  EXPECT_THROW(TaskOrder::frameTasks(p, given, 1, level), pcl_animseg::Error);  // given twice
}

// A body of 1500 points a frame has 187 tracked samples: its whole-body ICP searches in parallel
// (from 128 points) and its sums stay in point order, so the tracks are the same bit for bit on
// one thread (where it runs serially) and on three.
TEST(MotionTracking, SmallBodyTracksTheSameOnAnyNumberOfThreads) {
  const auto seq = chain(6, 1500, 4);
  seg::MotionTrackingParams params;
  const int threads = omp_get_max_threads();
  omp_set_num_threads(1);
  const seg::SampleTracks one = seg::trackSamples(*seq, params);
  omp_set_num_threads(3);
  const seg::SampleTracks three = seg::trackSamples(*seq, params);
  omp_set_num_threads(threads);
  ASSERT_GE(one.sample_points.size(), 128u);
  ASSERT_LT(one.sample_points.size(), 256u);
  ASSERT_EQ(one.poses.size(), three.poses.size());
  int differ = 0;
  for (std::size_t t = 0; t < one.poses.size(); ++t)
    for (std::size_t s = 0; s < one.poses[t].size(); ++s)
      differ += one.poses[t][s].matrix() != three.poses[t][s].matrix();
  EXPECT_EQ(differ, 0);
  EXPECT_EQ(one.residual, three.residual);
}

// Each expansion is an exact minimum cut: with two labels and every point starting on the first,
// the second's expansion can reach every labelling, so the expansions end on a labelling of the
// least energy (Potts: a cut edge costs its weight), which a search over all 2^12 labellings of
// small random problems finds too. A max-flow that put the wrong side of the cut in the sink's
// tree, or stopped short of the maximum flow, would end above it.
TEST(AlphaExpansions, TwoLabelsReachTheLeastEnergy) {
  constexpr int n = 12;
  for (unsigned seed = 1; seed <= 30; ++seed) {
    std::mt19937 rng(seed);
    std::uniform_real_distribution<double> uniform(0.0, 1.0);
    std::vector<std::vector<int>> cand(n, std::vector<int>{0, 1});
    std::vector<std::vector<double>> unary(n);
    for (int i = 0; i < n; ++i) unary[i] = {3.0 * uniform(rng), 3.0 * uniform(rng)};
    cand[n - 1] = {0};  // a point with one candidate keeps its label
    unary[n - 1] = {0.0};
    std::vector<std::vector<std::pair<int, double>>> edges(n);
    for (int i = 0; i < n; ++i)
      for (int j = i + 1; j < n; ++j)
        if (uniform(rng) < 0.3) edges[i].push_back({j, 2.0 * uniform(rng)});
    auto energy = [&](const std::vector<int>& l) {
      double e = 0.0;
      for (int i = 0; i < n; ++i) e += unary[i][cand[i].size() == 1 ? 0 : l[i]];
      for (int i = 0; i < n; ++i)
        for (const auto& [j, w] : edges[i]) e += l[i] != l[j] ? w : 0.0;
      return e;
    };
    double least = std::numeric_limits<double>::infinity();
    for (int bits = 0; bits < (1 << (n - 1)); ++bits) {
      std::vector<int> l(n, 0);
      for (int i = 0; i < n - 1; ++i) l[i] = (bits >> i) & 1;
      least = std::min(least, energy(l));
    }
    std::vector<int> label(n, 0);
    seg::detail::alphaExpansions(cand, unary, edges, label, false);
    EXPECT_EQ(label[n - 1], 0) << seed;
    EXPECT_NEAR(energy(label), least, 1e-9) << "seed " << seed;
  }
}
