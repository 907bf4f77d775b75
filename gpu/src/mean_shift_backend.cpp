// The CUDA engine behind MeanShiftSegmentation: gpu::MeanShift for the iteration, gpu trees for
// densities, with the keypoint pair rule of Eq. 5 realised by the same point groups as the CPU's
// JointKernelSum.
#include <pcl_animseg/error.h>
#include <pcl_animseg/gpu/device.h>
#include <pcl_animseg/gpu/gaussian_kdtree.h>
#include <pcl_animseg/gpu/mean_shift_backend.h>

namespace pcl_animseg {
namespace gpu {

std::string MeanShiftBackend::name() const { return deviceLabel(); }

void MeanShiftBackend::seekModes(const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric_plain,
                                 const Eigen::RowVectorXf& metric_key,
                                 const std::vector<char>& keypoint,
                                 const segmentation::MeanShiftParams& params, Eigen::MatrixXf& y,
                                 Eigen::VectorXf& density) {
  requireGpu();
  MeanShift ms;
  MeanShiftParams p;
  p.gkdtree = params.gkdtree;
  p.max_iterations = params.max_iterations;
  p.convergence = params.convergence;
  ms.setParams(p);
  ms.run(z, metric_plain, metric_key, keypoint, y, density);
  stats_ = ms.stats();
}

void MeanShiftBackend::density(const Eigen::MatrixXf& z, const Eigen::RowVectorXf& metric_plain,
                               const Eigen::RowVectorXf& metric_key,
                               const std::vector<char>& keypoint,
                               const segmentation::MeanShiftParams& params,
                               const Eigen::MatrixXf& queries, const std::vector<char>& query_key,
                               Eigen::VectorXf& out) {
  requireGpu();
  const Eigen::Index n = z.rows(), q = queries.rows();
  if (queries.cols() != z.cols()) throw Error("GPU density: queries and data differ in dimension");
  if (!keypoint.empty() && keypoint.size() != static_cast<std::size_t>(n))
    throw Error("GPU density: keypoint flags must have one entry per point");
  if (!query_key.empty() && query_key.size() != static_cast<std::size_t>(q))
    throw Error("GPU density: query flags must have one entry per query");
  out.setZero(q);
  if (q == 0) return;
  // Groups as on the CPU: non-keypoints for every query under the plain metric; keypoints under
  // the plain metric for plain queries and under the pair metric (Eq. 5) for keypoint queries.
  std::vector<Eigen::Index> plain, key;
  for (Eigen::Index i = 0; i < n; ++i) (!keypoint.empty() && keypoint[i] ? key : plain).push_back(i);
  std::vector<Eigen::Index> qplain, qkey;
  for (Eigen::Index r = 0; r < q; ++r)
    (!keypoint.empty() && !query_key.empty() && query_key[r] ? qkey : qplain).push_back(r);
  auto add = [&](const std::vector<Eigen::Index>& data, const std::vector<Eigen::Index>& rows,
                 const Eigen::RowVectorXf& metric, bool all_queries) {
    if (data.empty()) return;
    const std::size_t nr = all_queries ? static_cast<std::size_t>(q) : rows.size();
    if (nr == 0) return;
    Eigen::MatrixXf x(data.size(), z.cols());
    for (std::size_t i = 0; i < data.size(); ++i) x.row(i) = z.row(data[i]).cwiseProduct(metric);
    Eigen::MatrixXf qs(nr, z.cols());
    for (std::size_t r = 0; r < nr; ++r)
      qs.row(r) = queries.row(all_queries ? static_cast<Eigen::Index>(r) : rows[r])
                      .cwiseProduct(metric);
    GaussianKdTree tree(params.gkdtree);
    tree.build(x);
    Eigen::MatrixXf res;
    tree.filter(Eigen::MatrixXf::Ones(x.rows(), 1), qs, res);
    for (std::size_t r = 0; r < nr; ++r)
      out[all_queries ? static_cast<Eigen::Index>(r) : rows[r]] += res(r, 0);
  };
  add(plain, {}, metric_plain, true);
  add(key, qplain, metric_plain, false);
  add(key, qkey, metric_key, false);
}

std::shared_ptr<segmentation::MeanShiftDeviceBackend> makeMeanShiftBackend(bool check_now) {
  if (check_now) requireGpu();
  return std::make_shared<MeanShiftBackend>();
}

}  // namespace gpu
}  // namespace pcl_animseg
