#pragma once
/** \file gaussian_kdtree.h High-dimensional Gaussian filtering over a kd-tree of samples
 * (Adams, Gelfand, Dolson, Levoy: "Gaussian KD-Trees for Fast High-Dimensional Filtering",
 * SIGGRAPH 2009), the accelerator of the paper's mean shift (Sect. 3.3, Eq. 10).
 *
 * Written by us: none of the libraries we depend on (PCL, FLANN, Eigen) provides it. This CPU
 * class is the reference implementation; a GPU implementation offers the same interface and must
 * agree with it.
 *
 * The filter computes, for every query q,
 *
 *     out(q) = sum_j exp(-|q - p_j|^2 / 2) * values_j                               (Eq. 10)
 *
 * for N data points p_j (rows of `positions`, already divided by the bandwidth so that the
 * Gaussian has unit standard deviation) and per-point value vectors (rows of `values`). With
 * values = [z, 1] (homogeneous coordinates) one call gives both the numerator and the
 * denominator of the mean shift update (Eq. 8): no separate normalisation pass.
 *
 * How (Adams et al.'s three stages over a kd-tree whose leaves are the samples):
 *  - build: the data are split top-down along the longest side of each cell's bounding box, at
 *    the middle of the box, until a cell's longest side is at most `leaf_extent` (in units of the
 *    standard deviation) or it holds fewer than `min_leaf_points` points. Each leaf is one sample,
 *    placed at the mean of its points. The sampling factor N/M is reported by samplingFactor().
 *  - splat: each data point gives its value to the leaf that holds it (points are assigned during
 *    the build, so this is exact in mass and first moment; Adams et al. splat with importance
 *    samples because their samples are not the cells of the input).
 *  - blur: each sample gathers exp(-|s_l - s_m|^2 / 2) * V_m from every sample within
 *    `blur_radius` standard deviations (a range search with bounding-box pruning: the samples are
 *    few, so this stage is exact on the samples).
 *  - slice: each query interpolates the blurred sample values from the leaves reached by
 *    `slice_samples` importance samples. At a split, the samples are divided between the two
 *    children in proportion to the Gaussian mass of the query's slice kernel on each side, as in
 *    Adams et al., but the division is rounded instead of drawn at random, so that the filter is
 *    deterministic (no seed) and a query moving slightly gives a slightly different result (mean
 *    shift converges). Leaves reached are weighted by exp(-|q - s_l|^2 / (2 h^2)), h =
 *    `slice_sigma`, normalised to sum 1.
 *
 * The approximation thus replaces every data point by the mean of its cell (error of the order of
 * `leaf_extent` in the kernel's argument) and interpolates queries between nearby cells.
 * Thread-safe after build(); the stages run in parallel with OpenMP.
 */
#include <Eigen/Core>

#include <cstddef>
#include <memory>
#include <vector>

namespace pcl_animseg {
namespace filters {

/** \brief Knobs of the Gaussian kd-tree, in units of the kernel's standard deviation. */
struct GaussianKdTreeParams {
  /** Longest side of a leaf cell (Adams et al.'s eta). Smaller: more samples, more accurate. */
  float leaf_extent = 1.0f;
  /** A cell holding fewer points is not split further (bounds the sample count: N/M is at least
   * about half of it when the data are dense compared with leaf_extent). */
  int min_leaf_points = 1;
  /** Samples gather from samples within this distance (exp(-4.5) = 1% at 3). */
  float blur_radius = 3.0f;
  /** Importance samples per slice query. */
  int slice_samples = 8;
  /** Width of the slice interpolation kernel. */
  float slice_sigma = 0.5f;
};

/** \brief Gaussian kd-tree filter (see the file comment). */
class GaussianKdTree {
 public:
  using Ptr = std::shared_ptr<GaussianKdTree>;
  using ConstPtr = std::shared_ptr<const GaussianKdTree>;

  GaussianKdTree() = default;
  explicit GaussianKdTree(const GaussianKdTreeParams& params) : params_(params) {}

  void setParams(const GaussianKdTreeParams& params) { params_ = params; }
  const GaussianKdTreeParams& getParams() const { return params_; }

  /** \brief Builds the tree over N x d positions (already divided by the bandwidth). Throws
   * Error for an empty matrix or non-finite coordinates. */
  void build(const Eigen::MatrixXf& positions);

  /** \brief out (Q x v) = sum_j exp(-|q - p_j|^2/2) values_j for the rows q of `queries`
   * (Q x d); `values` is N x v. Splat + blur + slice. */
  void filter(const Eigen::MatrixXf& values, const Eigen::MatrixXf& queries,
              Eigen::MatrixXf& out) const;

  /** \brief The first two stages alone: blurred sample values (M x v). Mean shift filters the
   * same data values at moving queries, so it splats and blurs once and slices every iteration. */
  void splatBlur(const Eigen::MatrixXf& values, Eigen::MatrixXf& sample_values) const;

  /** \brief The third stage: out (Q x v) interpolated from blurred sample values (M x v). */
  void slice(const Eigen::MatrixXf& sample_values, const Eigen::MatrixXf& queries,
             Eigen::MatrixXf& out) const;

  /** \brief Slice of the rows of `queries` listed in `rows` only (the rest of `out` untouched):
   * mean shift stops moving converged points. */
  void slice(const Eigen::MatrixXf& sample_values, const Eigen::MatrixXf& queries,
             const std::vector<int>& rows, Eigen::MatrixXf& out) const;

  std::size_t numPoints() const { return leaf_of_point_.size(); }
  std::size_t numSamples() const { return static_cast<std::size_t>(samples_.cols()); }
  int dimension() const { return static_cast<int>(samples_.rows()); }
  /** \brief N / M. */
  double samplingFactor() const;
  /** \brief Sample (leaf) positions, d x M. */
  const Eigen::MatrixXf& samples() const { return samples_; }
  /** \brief The sample (leaf) holding data point j. */
  int leafOf(std::size_t j) const { return leaf_of_point_[j]; }
  /** \brief The leaf whose cell holds position q (d values, scaled like the data): the
   * tree's descent by its cuts. */
  int leafContaining(const float* q) const;
  /** \brief Bytes held by the tree (for the benchmark's memory report). */
  std::size_t memoryBytes() const;

 private:
  struct Node {
    int dim = -1;      // split dimension, -1 for a leaf
    float cut = 0.0f;  // split value: left holds coordinates <= cut
    int left = -1;
    int right = -1;
    int leaf = -1;     // sample index for a leaf
  };
  int buildNode(const Eigen::MatrixXf& pts, std::vector<int>& idx, int begin, int end, int depth);
  void computeBoxes(int node);
  void sliceOne(const float* q, const Eigen::MatrixXf& sample_values, float* out,
                std::vector<std::pair<int, int>>& stack, std::vector<int>& reached,
                std::vector<float>& dist) const;

  GaussianKdTreeParams params_;
  std::vector<Node> nodes_;
  Eigen::MatrixXf samples_;    // d x M
  Eigen::MatrixXf box_min_;    // d x nodes: bounding box of the samples under each node
  Eigen::MatrixXf box_max_;
  std::vector<int> leaf_of_point_;
  int root_ = -1;
  std::vector<Eigen::VectorXf> sample_list_;  // build-time only
};

/** \brief Brute-force Gauss transform, the reference for tests: out = sum_j exp(-|q-p_j|^2/2)
 * values_j over all data points (O(N Q d)). */
void bruteForceGaussTransform(const Eigen::MatrixXf& positions, const Eigen::MatrixXf& values,
                              const Eigen::MatrixXf& queries, Eigen::MatrixXf& out);

}  // namespace filters
}  // namespace pcl_animseg
