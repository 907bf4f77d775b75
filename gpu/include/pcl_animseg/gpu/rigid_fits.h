#pragma once
/** \file rigid_fits.h The rigid motions' ICP fits on the current CUDA device.
 *
 * \code
 * pcl_animseg::gpu::RigidFits gpu_fits;
 * pcl_animseg::segmentation::RigidMotionEstimation motion;
 * motion.setDevice(&gpu_fits);   // computeLevels / compute fit on the GPU
 * \endcode
 *
 * `animseg --device gpu|auto` uses one for the rigid motions when the mean-shift stage ran on
 * the GPU. A cluster of 1-8 blocks runs one fit's ICP passes (segmentation::fitRigidJob), a
 * thread per range of the source (icp_step::rangeBegin), the ranges split among the blocks, whose
 * threads search the nearest points of their ranges; a batch is one kernel launch. The arithmetic
 * and the order of every sum are the CPU's (segmentation/icp_step.h), and the nearest points come
 * from copies of the CPU's trees: the motions are the CPU's bit for bit.
 */
#include <pcl_animseg/segmentation/rigid_motion.h>

#include <memory>
#include <string>
#include <thread>
#include <vector>

namespace pcl_animseg {
namespace gpu {

namespace detail {
struct FrameStore;
struct FrameArrays;
struct KnnStore;
struct RigidSources;
}  // namespace detail

/** \brief segmentation::RigidFitDevice on the current CUDA device. */
class RigidFits : public segmentation::RigidFitDevice {
 public:
  RigidFits();
  ~RigidFits() override;
  std::string name() const override;
  /** \brief Throws Error on a CUDA failure or a surface without a tree. */
  void setSurfaces(const segmentation::DeviceFrames& surfaces) override;
  void setSources(const std::vector<const std::vector<double>*>& sources) override;
  /** \brief Throws Error on a CUDA failure, nothing set, or a job out of range. */
  void fit(const std::vector<segmentation::RigidFitJob>& jobs,
           const segmentation::RigidMotionParams& params, std::vector<double>& poses,
           std::vector<double>& rms) override;
  /** \brief FlatKdTree3::knn of every query on the device, a query per thread (the same rows
   * in the same order; k = 1: FlatKdTree3::nearest without a bound), the trees uploaded for this
   * call alone (trees kept before stay kept). Returns false for k < 1 or k > 32 (the caller
   * searches on the CPU); throws Error on a CUDA failure, a missing tree or a query's tree out
   * of range. */
  bool knn(const std::vector<const FlatKdTree3*>& trees, int k, const std::vector<float>& queries,
           const std::vector<int>& tree_of, std::vector<int>& rows,
           std::vector<int>& count) override;
  /** \brief The trees packed and uploaded once for the knnOn() calls that follow (kept until the
   * next keepKnnTrees() or knn() call, or this object's end); throws Error on a CUDA failure or a
   * missing tree. */
  long long keepKnnTrees(const std::vector<const FlatKdTree3*>& trees) override;
  /** \brief knn() against the kept trees; false where `token` is not the last keepKnnTrees()'s
   * or k is out of range. */
  bool knnOn(long long token, int k, const std::vector<float>& queries,
             const std::vector<int>& tree_of, std::vector<int>& rows,
             std::vector<int>& count) override;
  void dropKnnTrees(long long token) override;
  /** \brief The refinement's motion check against the kept trees (a thread per residual, each
   * copy's nearest point found there); false where `token` is not the last keepKnnTrees()'s;
   * throws Error on a CUDA failure or jobs that do not match the trees. */
  bool motionResiduals(long long token, const segmentation::MotionCheckJobs& jobs,
                       std::vector<float>& out) override;
  /** \brief FlatKdTree3::within from every query against the kept trees, a query per thread,
   * each row's least distance kept by an atomic minimum (the same values as the CPU's: a
   * minimum does not depend on the order); false where `token` is not the last
   * keepKnnTrees()'s; throws Error on a CUDA failure or a query's tree or the bounds out of
   * range. */
  bool leastDistances(long long token, const std::vector<float>& queries,
                      const std::vector<int>& tree_of, const std::vector<float>& bound2,
                      std::vector<float>& out) override;
  /** \brief math::gmmEM of every job on the device, a block each, the same bits as on the
   * cores; false for a job of more than 8 components (the caller fits on the cores); throws Error
   * on a CUDA failure, a job without points, or a covariance that is not positive definite. */
  bool fitMixtures(const std::vector<segmentation::MixtureFitJob>& jobs,
                   const math::GMMOptions& options) override;
  /** \brief Every job's rigidScore (segmentation/rigid_motion.h), a block per job, against the
   * surfaces and sources set; false (the caller scores on the CPU) where a job has more than 512
   * probes; throws Error on a CUDA failure, nothing set, or a job out of range. */
  bool scores(const std::vector<segmentation::RigidScoreJob>& jobs,
              std::vector<double>& out) override;
  /** \brief Fits and kernel launches since construction. */
  long long fits() const { return fits_; }
  long long batches() const { return batches_; }
  /** \brief Score batches (scores()) since construction. */
  long long scoreBatches() const { return score_batches_; }

  /** \brief Blocks per fit: 0 (the default) chooses per batch (enough that a block searches
   * about a point per thread while every fit's cluster runs at once); 1, 2, 4 or 8 asks for that
   * many where the device runs such clusters (fewer otherwise). The motions are the same bits
   * whatever the size. */
  void setClusterSize(int blocks) { cluster_ = blocks; }
  /** \brief The blocks per fit of the last batch (0 before the first). */
  int lastClusterSize() const { return last_cluster_; }

 private:
  std::unique_ptr<detail::FrameStore> surfaces_;
  std::unique_ptr<detail::FrameArrays> packed_;  // the surfaces' host buffers, reused
  std::thread locking_;  // page-locks packed_'s buffers after an upload, for the next one
  std::unique_ptr<detail::RigidSources> sources_;
  std::unique_ptr<detail::KnnStore> knn_;  // the kept trees
  long long knn_token_ = 0;                // the kept trees' token (0: none kept)
  long long knn_keeps_ = 0;                // keepKnnTrees() calls that uploaded trees
  long long fits_ = 0, batches_ = 0, score_batches_ = 0;
  int cluster_ = 0, last_cluster_ = 0;
};

}  // namespace gpu
}  // namespace pcl_animseg
