#pragma once
// Internal: the motion method's fits, residuals and point costs on the GPU (motion_tracking.cpp
// packs the segmentation structures into these plain arrays; tracking_kernels.cu runs them). No
// Eigen or PCL here: this header is read by nvcc.
#include <pcl_animseg/gpu/device_array.h>
#include <pcl_animseg/math/gmm_em.h>
#include <pcl_animseg/packed_vector.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <functional>
#include <memory>
#include <thread>
#include <utility>
#include <vector>

namespace pcl_animseg {
namespace gpu {
namespace detail {

/** A kd-tree node of FlatKdTree3 with its indices made global: an inner node's children index
 * the nodes, a leaf's [a, b) the points. */
struct TrackNode {
  float split;
  int dim;  // -1: leaf
  int a;
  int b;
};

/** A pose as 12 doubles: the rotation row by row, then the translation. */
constexpr int kPoseDoubles = 12;

/** Host memory page-locked (cudaHostRegister) for the copies out of it while it stays where it
 * is. A copy from pageable memory goes through the driver's staging buffers; from locked memory
 * it goes straight to the device (the rigid motions' part surfaces at 800k, about 28 MB: 5-6 ms
 * pageable, 2 ms locked). The memory must be unlocked before it is freed or moved (a vector
 * reallocated): unlock(), or the lock's end. */
class HostLock {
 public:
  HostLock() = default;
  ~HostLock() { unlock(); }
  HostLock(HostLock&& o) noexcept : p_(o.p_), bytes_(o.bytes_) { o.p_ = nullptr, o.bytes_ = 0; }
  HostLock& operator=(HostLock&& o) noexcept;
  HostLock(const HostLock&) = delete;
  HostLock& operator=(const HostLock&) = delete;
  /** [p, p + bytes) locked, unless it is already; what was locked before is unlocked first.
   * False where CUDA refuses (no GPU, or the range overlaps one locked elsewhere): copies from it
   * then go pageable, as they would without the lock. */
  bool lock(const void* p, std::size_t bytes);
  void unlock();

 private:
  void* p_ = nullptr;
  std::size_t bytes_ = 0;
};

/** The frames on the host, packed. */
struct FrameArrays {
  int frames = 0;
  double normal_cos = 0.3;
  double clip = 4.0;
  PackedVector<TrackNode> nodes;
  std::vector<int> root;        // per frame: root node, -1 when empty
  PackedVector<float> points;   // 4 per point (x, y, z, 0), leaf order
  PackedVector<float> normals;  // 4 per point
  std::vector<double> spacing;  // per frame
  std::vector<int> unoriented;  // per frame
  std::vector<int> point0;      // per frame: its first point (leaf order), plus the end
  /** The large arrays' buffers where page-locked (lockFrameArrays), kept locked while they stay
   * (a packing into the same buffers uploads from locked memory again); declared after the
   * arrays, so that they are unlocked before the arrays are freed. packDeviceFrames unlocks a
   * buffer before it grows it. */
  HostLock nodes_lock, points_lock, normals_lock;
};

/** Page-locked host memory (cudaHostAlloc), grown as needed and kept: a batch's inputs go up
 * from it and its results come back through it, so that the copies run without the driver's
 * own staging and a batch waits once, at its end. */
class PinnedHost {
 public:
  /** A batch's buffer grows in the caller's thread up to this many bytes, and on a thread of
   * its own up to kGrowBeside (forBatch). */
  static constexpr std::size_t kGrowHere = std::size_t(1) << 20;
  static constexpr std::size_t kGrowBeside = std::size_t(4) << 20;

  PinnedHost() = default;
  ~PinnedHost();
  PinnedHost(const PinnedHost&) = delete;
  PinnedHost& operator=(const PinnedHost&) = delete;
  /** At least `bytes` (what it held is not kept when it grows); throws Error on a CUDA failure. */
  unsigned char* reserve(std::size_t bytes);
  /** For a batch of `bytes`: the buffer where it holds them or where it can grow to them here
   * cheaply (at most kGrowHere); else null, and the batch goes without page-locked memory.
   * Page-locking is slow: growing to the one-off batches of the motion method at 800k (the
   * sample edges' 8.9 MB of inputs, the first dissolve costs' 14 MB of results) took 9-16 ms of
   * the caller's thread each, more than a pageable copy of them. A batch of at most kGrowBeside
   * bytes may come again, so a buffer for it is grown on a thread of its own, taken by a later
   * batch once it is ready. */
  unsigned char* forBatch(std::size_t bytes);
  /** Grows the buffer to hold `bytes` on a thread of its own, unless a growth is under way:
   * page-locking takes about as long as the copy it speeds up, so it runs beside the caller's
   * work. awaitGrown or a later forBatch takes the grown buffer. */
  void growBeside(std::size_t bytes);
  /** Waits for a growth under way (growBeside) and takes it; returns the buffer where it holds
   * `bytes`, else null (the growth failed: the caller goes without page-locked memory). */
  unsigned char* awaitGrown(std::size_t bytes);
  /** The buffer (null before the first reserve). */
  unsigned char* data() const { return static_cast<unsigned char*>(block_.ptr); }
  /** The buffer's address for kernels (pinned memory is mapped into the device's address
   * space), after reserve(). */
  void* devicePtr() const { return block_.device; }

 private:
  struct Block {
    void* ptr = nullptr;
    void* device = nullptr;
    std::size_t bytes = 0;
  };
  // What a buffer for `bytes` is grown to: half as much again, so that a slowly growing batch
  // size does not page-lock anew for every batch.
  static std::size_t grownSize(std::size_t bytes) {
    return std::max<std::size_t>(bytes + bytes / 2, 4096);
  }
  static Block allocate(std::size_t bytes);  // throws Error
  static void release(Block& b);
  void adopt(Block& b);  // b in place of block_ when larger (the smaller one freed)
  void takeGrown();      // a finished growth's buffer adopted (grower_ joined)
  Block block_;
  // The growth on a thread of its own: `grown_` once `grown_ready_`.
  std::thread grower_;
  Block grown_;
  std::atomic<bool> grown_ready_{false};
};

/** Waits for the work queued on the calling thread's stream by polling an event and yielding
 * the core between polls, for a thread beside other work: a spinning wait (the default
 * synchronisation) holds a core that the other work's threads need, and a sleeping one
 * (blocking sync) adds its wake-up to every call. */
class YieldingWait {
 public:
  YieldingWait() = default;
  ~YieldingWait();
  YieldingWait(const YieldingWait&) = delete;
  YieldingWait& operator=(const YieldingWait&) = delete;
  /** Throws Error on a CUDA failure (a kernel fault of the work waited for among them). */
  void wait();

 private:
  void* event_ = nullptr;
};

/** The frames on the device (setFrames), kept for the calls that follow. */
struct FrameStore {
  int frames = 0;
  double normal_cos = 0.3;
  double clip = 4.0;
  /** Where set, the store whose frame arrays (nodes ... unoriented) these calls read: a fork
   * (MotionTracking::fork) has only its own batch buffers. */
  const FrameStore* shared = nullptr;
  /** Whether a batch's results are waited for yielding the core (YieldingWait) instead of
   * spinning: a fork's calls come from a thread beside the caller's work (MotionTracking::fork). */
  bool yield_while_waiting = false;
  YieldingWait yielding;
  DeviceArray<TrackNode> nodes;
  DeviceArray<int> root;
  DeviceArray<float> points, normals;
  DeviceArray<double> spacing;
  DeviceArray<int> unoriented;
  std::vector<int> point0;  // host copy: per frame its first point, plus the end
  /** Residual batches' buffers, grown as needed and kept: a merge loop asks for hundreds of
   * small batches, and an allocation each would cost more than the batch. A batch's inputs
   * (points, source ranges, motions, jobs) go up as one block through `staging`: one copy per
   * batch instead of four, each a synchronous round trip of some 10-25 us. */
  DeviceMemory job_in, job_out;
  PinnedHost staging, results;
  /** A batch too large for `staging` or `results` (PinnedHost::forBatch) goes through these
   * instead: its inputs packed into pageable memory, its results written to device memory of
   * their own (let go once they are copied back) and copied back (`results_pageable` says which
   * way the batch in flight went). */
  PackedVector<unsigned char> pageable_in;
  PackedVector<double> pageable_out;
  DeviceMemory results_on_device;
  bool results_pageable = false;
  /** The rigid fits' matches (an int and a float per source point of a batch), how many
   * clusters of 2, 4 and 8 blocks run at once (-1: not measured yet), and whether the fits'
   * kernel may have its dynamic shared memory (set once, before its first launch or query). */
  DeviceMemory rigid_scratch;
  int rigid_clusters[3] = {-1, -1, -1};
  bool rigid_shared_set = false;
  bool large_fits_set = false;  ///< the large part fits' shared memory allowed (runPartFits)
  bool large_score_fits_set = false;  ///< the same for runScoreFits
  /** Calls by kind (residuals, point costs, part fits, rigid fits, scored part fits): count, jobs
   * and wall seconds, printed on stderr when the store goes and ANIMSEG_MS_TIMING is set. */
  struct CallStats {
    long calls = 0, jobs = 0;
    double seconds = 0.0;
  };
  static constexpr int kCallKinds = 5;
  CallStats stats[kCallKinds];
  /** The labels' copies of the reference (runMovedNearest) before they go up: kept, pageable. */
  PackedVector<float> moved_host;
};

// Adds a call's wall time to its kind's statistics when it returns.
class CallTimer {
 public:
  CallTimer(FrameStore& store, int kind, std::size_t jobs)
      : s_(store.stats[kind]), t0_(std::chrono::steady_clock::now()) {
    ++s_.calls;
    s_.jobs += static_cast<long>(jobs);
  }
  ~CallTimer() {
    s_.seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0_).count();
  }

 private:
  FrameStore::CallStats& s_;
  std::chrono::steady_clock::time_point t0_;
};

/** Prints a store's call statistics (see FrameStore::stats) under ANIMSEG_MS_TIMING. */
void reportCalls(const FrameStore& store, const char* owner);

/** Puts `in` on the device as `store`'s frames, in place of any there: a buffer that holds its
 * array is kept, others are allocated again; the store's batch buffers are not touched. The
 * arrays go from where they are, page-locked (lockFrameArrays) or not. */
void uploadFrames(const FrameArrays& in, FrameStore& store);
/** Locks `in`'s large buffers (HostLock) for the uploads to come, where they are not locked
 * already; no CUDA error escapes (a buffer left unlocked uploads pageable). Locking a buffer costs
 * about what the copy saves, so it pays only for a buffer uploaded again (RigidFits' surfaces);
 * the motion method's frames, uploaded once, go pageable (27.9 MB at 800k: a median of 5.7 ms
 * pageable, 5.3 ms locked on the way, locking included, over four leases). */
void lockFrameArrays(FrameArrays& in);

/** The tracking's fits besides the frames. */
struct TrackingArrays {
  int samples = 0;
  int iterations = 8;
  std::vector<double> source, probe;            // 6 per point: position, normal
  std::vector<int> source_begin, probe_begin;   // per sample, plus the end
  std::vector<int> adjacency, adjacency_begin;  // sample graph, CSR
  std::vector<int> level;                       // frames x samples
  std::vector<int> before, two_before;          // per frame
  std::vector<double> global;                   // frames x 12
  std::vector<int> tasks;  // tasks t * samples + s, wave after wave (a topological order)
};

/** Fits every task; poses (frames x samples x 12, the reference frame's entries the identity)
 * and residual (frames x samples) are filled. Returns the seconds spent (uploads, kernels,
 * downloads). Throws Error on a CUDA failure. */
double runTracking(const FrameStore& frames, const TrackingArrays& in, std::vector<double>& poses,
                   std::vector<double>& residual);

/** runTracking() as the frames come (MotionTracking::beginSamples .. endSamples): the
 * constructor uploads `in` but its tasks (`level` and `global` as given: their entries for the
 * frames to come are filled by frames()), frames() uploads some frames' global poses (12 doubles
 * each), levels and tasks (`samples` each, frame after frame, in a topological order) and starts
 * their fits as one kernel on the calling thread's stream without waiting, end() waits for them
 * and downloads poses and residuals as runTracking does. Every call from one thread. Throws Error
 * on a CUDA failure. */
class TrackingStream {
 public:
  TrackingStream(const FrameStore& frames, const TrackingArrays& in);
  ~TrackingStream();
  TrackingStream(const TrackingStream&) = delete;
  TrackingStream& operator=(const TrackingStream&) = delete;
  void frames(const std::vector<int>& frames, const double* global, const int* level,
              const int* tasks);
  /** Starts `n` tasks (a topological order, after the earlier calls') whose frames' levels and
   * global poses are on the device: those the constructor uploaded, or a frames() call's. */
  void tasks(const int* tasks, std::size_t n);
  /** Returns the seconds since the constructor began. */
  double end(std::vector<double>& poses, std::vector<double>& residual);

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/** A residual job: source, motion (12 doubles), frame. */
struct ResidualJob {
  int source;
  int motion;
  int frame;
};

/** One residual per job (points: 6 per point; source_begin: per source plus the end): a thread
 * per point when the jobs' sources hold at most point_parallel_limit points in all, else a warp
 * per job. */
void runResiduals(FrameStore& frames, const std::vector<double>& points,
                  const std::vector<int>& source_begin, const std::vector<double>& motions,
                  const std::vector<ResidualJob>& jobs, long long point_parallel_limit,
                  std::vector<double>& out);

/** A point-cost job: point, motion (frames x 12 doubles). */
struct PointCostJob {
  int point;
  int motion;
};

/** One point cost per job: the surface errors summed over the frames but `ref`. */
void runPointCosts(FrameStore& frames, int ref, bool per_frame, const std::vector<double>& points,
                   const std::vector<double>& motions, const std::vector<PointCostJob>& jobs,
                   std::vector<double>& out);

/** A part fit: source, start motion, frame, the residual to beat, the match distance. */
struct PartFitJob {
  int source;
  int motion;
  int frame;
  double r0;
  double max_dist;
};

/** segmentation::PartFitJobs: icp() of each job (`iterations` steps) kept when its residual is at
 * most r0, else the start; one warp each; 12 doubles per job in `poses`, and where `residual` is
 * given, each kept pose's residual (runResiduals' value) into it. */
void runPartFits(FrameStore& frames, const std::vector<double>& points,
                 const std::vector<int>& source_begin, const std::vector<double>& motions,
                 const std::vector<PartFitJob>& jobs, int iterations, std::vector<double>& poses,
                 std::vector<double>* residual = nullptr);

/** A score-and-fit job (segmentation::ScoreFitJobs): its starts (motions first .. first + count
 * - 1, at most kScoreFitStarts) with their places, its base, the match distance. */
constexpr int kScoreFitStarts = 8;
struct ScoreFitJob {
  int source;
  int frame;
  int first;
  int count;
  int place[kScoreFitStarts];
  int base_place;
  double base_score;
  double max_dist;
};

/** segmentation::ScoreFitJobs in one call: each job's starts scored (runResiduals' values, into
 * `scores`, one per start), its winner chosen as score_fit.h's scoreFitWinner does (`fitted`:
 * its index among the job's starts, -1 for none), and where a start wins, runPartFits' fit from
 * it with r0 its score (`poses`: 12 doubles per job, the identity where nothing is fitted). */
void runScoreFits(FrameStore& frames, const std::vector<double>& points,
                  const std::vector<int>& source_begin, const std::vector<double>& motions,
                  const std::vector<ScoreFitJob>& jobs, std::size_t starts, int iterations,
                  std::vector<double>& scores, std::vector<int>& fitted,
                  std::vector<double>& poses);

/** A rigid motions' fit (segmentation::RigidFitJob) with its source's range: points
 * [source_begin, source_begin + source_count) of the packed sources (x, y, z doubles). */
struct RigidJob {
  int source_begin;
  int source_count;
  int surface;
  int wide;
  long long scratch_begin;  // where its matches start in the batch's scratch (runRigidFits)
  double spacing;
  double part_diag;
  double start[kPoseDoubles];
};

/** segmentation::RigidMotionParams as the passes use them; max_turn = acos(0.99999), computed
 * on the host as the CPU computes it. */
struct RigidParams {
  int max_iterations;
  double max_correspondence_spacings;
  double coarse_distance;
  double transformation_epsilon;
  double relative_mse_epsilon;
  double max_turn;
};

/** Trees for k-NN queries (FlatKdTree3's nodes, points and input rows, every tree after the
 * other, indices made global). */
struct KnnTrees {
  PackedVector<TrackNode> nodes;
  std::vector<int> root;       // per tree: root node, -1 when empty
  std::vector<int> size;       // per tree: points
  PackedVector<float> points;  // 4 per point (x, y, z, 0), leaf order
  std::vector<int> rows;       // per point: its row in its own tree
};

/** The largest k that runKnn takes. */
constexpr int kMaxKnn = 32;

/** KnnTrees on the device. */
struct KnnStore {
  int trees = 0;
  DeviceArray<TrackNode> nodes;
  DeviceArray<float> points;
  DeviceArray<int> rows, root, size;
  std::vector<int> first;  // per tree: its first point among all (host copy; trees + 1 entries)
};

/** Uploads `trees` into `store` (in place of the trees there). */
void uploadKnnTrees(const KnnTrees& trees, KnnStore& store);

/** FlatKdTree3::knn (flat_kdtree.h) of every query (x, y, z in `queries`) against tree
 * tree_of[q] (< store.trees) of `store`: the same rows in the same order; k slots per query in
 * `rows` (-1 past count[q]). 1 <= k <= kMaxKnn (k = 1: nearest() without a bound, as
 * FlatKdTree3::knn). */
void runKnn(const KnnStore& store, int k, const std::vector<float>& queries,
            const std::vector<int>& tree_of, std::vector<int>& rows, std::vector<int>& count);

/** One mixture's EM for runMixtureFits: its points' first index and count (x, y, z each). */
struct MixtureJob {
  long long first;
  int n;
};
/** What runMixtureFits returns per job: gmm_em's mixture, the mean log-likelihood, the
 * iterations, whether it converged, and the first component that was not positive definite (or
 * -1). */
struct MixtureResult {
  math::gmm_em::Mixture<math::gmm_em::kMaxDeviceComponents> m;
  double log_likelihood;
  int iterations;
  int converged;
  int bad;
};

/** math::gmmEM of every job on the device, a block each (gmm_em.h's arithmetic, every sum in
 * point order: the same bits): `points` holds x, y, z of n_points points, `results` the jobs'
 * starts on the way in (their m) and their fits on the way out. */
void runMixtureFits(const double* points, std::size_t n_points, const std::vector<MixtureJob>& jobs,
                    int max_iterations, double tolerance, double regularization,
                    std::vector<MixtureResult>& results);

/** RigidFitDevice::leastDistances on `store`'s trees (the caller has checked the sizes): out
 * gets store.first.back() values, each row's least squared distance or +infinity. */
void runLeastDistances(const KnnStore& store, const std::vector<float>& queries,
                       const std::vector<int>& tree_of, const std::vector<float>& bound2,
                       std::vector<float>& out);

/** RigidFitDevice::motionResiduals (segmentation::MotionCheckJobs, in its arrays) on `store`'s
 * trees, one per frame (`frames` of them; the caller has checked the sizes): out[r] for each of
 * the `residuals`. */
struct MotionCheckArrays {
  const double* starts;
  const int* part;
  const int* own;
  int residuals;
  const double* motions;  // per part and frame: 12
  const char* valid;      // per part and frame
  int parts, frames;
  const int* scored;
  int n_scored;
  const double* spacing;  // per frame
  const float* normals;   // 3 per tree row, tree after tree
  std::size_t normal_floats;
  double cap;
};
void runMotionCheck(const KnnStore& store, const MotionCheckArrays& in, float* out);

/** segmentation::kMovedUndecided (motion_device.h, which nvcc does not read). */
constexpr int kMovedUndecided = -2;

/** segmentation::MotionDevice::nearestMoved on `frames`' frames: `n` copies per frame (of the
 * reference points `order`, n of them), written by `fill` (8 floats each, frame after frame);
 * `pick` gets one entry per point of every frame (leaf order, frame after frame). */
void runMovedNearest(FrameStore& frames, const std::vector<int>& order, int k, double normal_cos,
                     const std::function<void(float*)>& fill, std::vector<int>& pick);

/** The largest cluster of blocks that one rigid fit runs on (thread block clusters, sm_90). */
constexpr int kRigidMaxCluster = 8;

/** The order in which a rigid fit searches a source's points (x, y, z per point): within each of
 * kRigidMaxCluster groups of whole ranges (group g: icp_step::rangeBegin of ranges
 * [g * kSumRanges / kRigidMaxCluster, (g + 1) * kSumRanges / kRigidMaxCluster)), by the Morton
 * code of the point in the source's bounding box (each entry a point's index in the source). A
 * block of a cluster searches whole groups. Which thread searches a point does not change its
 * match, only how far apart the lanes of a warp walk. */
std::vector<int> rigidSearchOrder(const std::vector<double>& xyz);

/** The cluster size (1, 2, 4 or 8 blocks per fit) for a batch of `jobs` fits whose largest
 * source has `max_points` points: for sources of more than two points per thread, enough blocks
 * that each searches about a point per thread, as long as every job's cluster runs at once; 1
 * for smaller sources, and where the device or the build has no clusters.
 * `forced` > 0: that size, or the largest below it that the device runs. */
int rigidClusterSize(FrameStore& store, int jobs, int max_points, int forced = 0);

/** A score of segmentation::rigidScore: `probes` of the source's source_count points from
 * source_begin (x, y, z doubles each; point k source_count / probes), under `pose`, onto surface
 * `surface`. */
struct RigidScoreJob {
  int source_begin;
  int source_count;
  int surface;
  int probes;
  double pose[kPoseDoubles];
};

/** The most probes a score job may have (runRigidScores' shared memory). */
constexpr int kRigidScoreMaxProbes = 512;

/** Every job's rigidScore into `out`, a block per job (at most kRigidScoreMaxProbes probes). */
void runRigidScores(FrameStore& surfaces, const DeviceArray<double>& sources,
                    const std::vector<RigidScoreJob>& jobs, std::vector<double>& out);

/** segmentation::fitRigidJob for every job, one cluster of `cluster` blocks each (see
 * rigidClusterSize): poses (12 doubles per job) and rms. `surfaces`: the parts' trees as frames
 * (their spacing and orientation unused); `sources`: the packed sources on the device, `orders`
 * their rigidSearchOrder()s packed the same way. The same results for every cluster size. */
void runRigidFits(FrameStore& surfaces, const DeviceArray<double>& sources,
                  const DeviceArray<int>& orders, const std::vector<RigidJob>& jobs,
                  const RigidParams& params, int cluster, std::vector<double>& poses,
                  std::vector<double>& rms);

}  // namespace detail
}  // namespace gpu
}  // namespace pcl_animseg
