#include <pcl_animseg/error.h>
#include <pcl_animseg/features/signature.h>

#include <pcl/conversions.h>

#include <Eigen/Cholesky>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>

namespace pcl_animseg {
namespace {

constexpr double kPi = 3.14159265358979323846;

/** Monomials of degree <= 3 in (a, b), in the order 1 a b a2 ab b2 a3 a2b ab2 b3. */
template <int NC>
inline void monomials(double a, double b, Eigen::Matrix<double, NC, 1>& phi) {
  phi(0) = 1.0;
  if (NC > 1) { phi(1) = a; phi(2) = b; }
  if (NC > 3) { phi(3) = a * a; phi(4) = a * b; phi(5) = b * b; }
  if (NC > 6) { phi(6) = a * a * a; phi(7) = a * a * b; phi(8) = a * b * b; phi(9) = b * b * b; }
}

/** Derivatives of the monomials along a and b. */
template <int NC>
inline void monomialGrad(double a, double b, Eigen::Matrix<double, NC, 1>& da,
                         Eigen::Matrix<double, NC, 1>& db) {
  da.setZero();
  db.setZero();
  if (NC > 1) { da(1) = 1.0; db(2) = 1.0; }
  if (NC > 3) { da(3) = 2.0 * a; da(4) = b; db(4) = a; db(5) = 2.0 * b; }
  if (NC > 6) {
    da(6) = 3.0 * a * a; da(7) = 2.0 * a * b; da(8) = b * b;
    db(7) = a * a; db(8) = 2.0 * a * b; db(9) = 3.0 * b * b;
  }
}

/** Weighted LS height field through the points (a, b, z) whose gradient also matches the
 * points' normals (ga, gb) = (-n_u / n_n, -n_v / n_n): three equations per point instead of one
 * make the cubic far less noisy on sparse random samples, and the system stays exactly
 * covariant under rotations of (u, v) (the gradient rotates with them). Coefficients are padded
 * to 10 (zeros above the fitted degree). */
template <int NC>
bool fitHeight(const double* a, const double* b, const double* z, const double* ga,
               const double* gb, const double* w, int m, Eigen::Matrix<double, 10, 1>& coef) {
  // Lower triangle accumulated by hand: Eigen's selfadjoint rankUpdate on fixed 10-vectors goes
  // through its general product kernel and was a third of the signature's time.
  double A[NC][NC] = {};
  double rhs[NC] = {};
  Eigen::Matrix<double, NC, 1> phi, da, db;
  double sw = 0.0;
  for (int i = 0; i < m; ++i) {
    monomials<NC>(a[i], b[i], phi);
    const double wi = w[i];
    sw += wi;
    if (ga[i] == ga[i]) {  // NaN marks a normal too tilted to give a slope
      monomialGrad<NC>(a[i], b[i], da, db);
      for (int r = 0; r < NC; ++r) {
        const double pr = wi * phi(r), ar = wi * da(r), br = wi * db(r);
        for (int c = 0; c <= r; ++c) A[r][c] += pr * phi(c) + ar * da(c) + br * db(c);
        rhs[r] += pr * z[i] + ar * ga[i] + br * gb[i];
      }
    } else {
      for (int r = 0; r < NC; ++r) {
        const double pr = wi * phi(r);
        for (int c = 0; c <= r; ++c) A[r][c] += pr * phi(c);
        rhs[r] += pr * z[i];
      }
    }
  }
  Eigen::Matrix<double, NC, NC> M;
  Eigen::Matrix<double, NC, 1> v;
  for (int r = 0; r < NC; ++r) {
    v(r) = rhs[r];
    for (int c = 0; c <= r; ++c) M(r, c) = M(c, r) = A[r][c];
  }
  // A whisper of ridge regularisation only guards against exactly singular systems.
  M.diagonal().array() += 1e-10 * sw;
  Eigen::LDLT<Eigen::Matrix<double, NC, NC>> ldlt;
  ldlt.compute(M);
  if (ldlt.info() != Eigen::Success || !ldlt.isPositive()) return false;
  // Reject near-singular fits (points nearly on a line): they would extrapolate wildly.
  const auto d = ldlt.vectorD();
  if (!(d.minCoeff() > 1e-7 * d.maxCoeff())) return false;
  const Eigen::Matrix<double, NC, 1> c = ldlt.solve(v);
  if (!c.allFinite()) return false;
  coef.setZero();
  coef.template head<NC>() = c;
  return true;
}

/** s_q = normal of the height field z(a, b) = sum c_i m_i(a, b) at sample q, dotted with the unit
 * direction from p to the sample, in float and in passes that vectorise (the double, one sample
 * at a time version was half of the signature's time; float keeps ~1e-7 of relative accuracy,
 * far below the invariance tolerance of 1%). `den2` is scratch of q_count floats; no two arrays
 * overlap (__restrict: eleven arrays are more than the compiler checks for overlap at run time). */
void sampleNormals(const float* c, int q_count, const float* __restrict a,
                   const float* __restrict b, const float* __restrict aa,
                   const float* __restrict ab, const float* __restrict bb,
                   const float* __restrict aaa, const float* __restrict aab,
                   const float* __restrict abb, const float* __restrict bbb,
                   float* __restrict den2, float* __restrict s) {
  const float c1 = c[1], c2 = c[2], c3 = c[3], c4 = c[4], c5 = c[5], c6 = c[6], c7 = c[7],
              c8 = c[8], c9 = c[9];
  for (int q = 0; q < q_count; ++q) {
    const float z = c1 * a[q] + c2 * b[q] + c3 * aa[q] + c4 * ab[q] + c5 * bb[q] + c6 * aaa[q] +
                    c7 * aab[q] + c8 * abb[q] + c9 * bbb[q];
    const float za = c1 + 2.0f * c3 * a[q] + c4 * b[q] + 3.0f * c6 * aa[q] + 2.0f * c7 * ab[q] +
                     c8 * bb[q];
    const float zb = c2 + c4 * a[q] + 2.0f * c5 * b[q] + c7 * aa[q] + 2.0f * c8 * ab[q] +
                     3.0f * c9 * bb[q];
    // normal (-za, -zb, 1) against the direction (a, b, z) from p to the sample.
    s[q] = z - za * a[q] - zb * b[q];
    den2[q] = std::max((1.0f + za * za + zb * zb) * (aa[q] + bb[q] + z * z), 1e-30f);
  }
  // The square root separately: with errno semantics (the default) the compiler keeps sqrtf
  // scalar, so the one pass that needs it is written with SSE where there is SSE.
  int q = 0;
#if defined(__SSE2__)
  for (; q + 4 <= q_count; q += 4)
    _mm_storeu_ps(s + q, _mm_div_ps(_mm_loadu_ps(s + q), _mm_sqrt_ps(_mm_loadu_ps(den2 + q))));
#endif
  for (; q < q_count; ++q) s[q] /= std::sqrt(den2[q]);
}

}  // namespace

void SignatureLayout::validate() const {
  if (radial < 1 || angular < 2 || radial_freqs < 1 || angular_freqs < 1 ||
      radial_freqs > radial || angular_freqs > angular / 2 + 1 || radial > 4096 || angular > 4096)
    throw Error("signature layout R=" + std::to_string(radial) + " S=" + std::to_string(angular) +
                " R'=" + std::to_string(radial_freqs) + " S'=" + std::to_string(angular_freqs) +
                " is invalid: need S >= 2, 1 <= R' <= R and 1 <= S' <= S/2 + 1");
}

Eigen::Vector3f defaultTangent(const Eigen::Vector3f& n) {
  Eigen::Vector3f e = Eigen::Vector3f::Zero();
  int a = 0;
  n.cwiseAbs().minCoeff(&a);
  e(a) = 1.0f;
  return n.cross(e).normalized();
}

DiscSignature::DiscSignature(const SignatureLayout& layout) : layout_(layout) {
  layout_.validate();
  const int R = layout_.radial, S = layout_.angular;
  const int Rp = layout_.radial_freqs, Sp = layout_.angular_freqs;
  const std::size_t Q = static_cast<std::size_t>(R) * S;
  for (auto* v : {&a_, &b_, &aa_, &ab_, &bb_, &aaa_, &aab_, &abb_, &bbb_}) v->resize(Q);
  for (int k = 0; k < S; ++k)
    for (int l = 0; l < R; ++l) {
      const double rr = static_cast<double>(l + 1) / R;  // 2lh/R over rho = 2h
      const double a = rr * std::cos(2.0 * kPi * k / S), b = rr * std::sin(2.0 * kPi * k / S);
      const std::size_t q = static_cast<std::size_t>(k) * R + l;
      a_[q] = static_cast<float>(a);
      b_[q] = static_cast<float>(b);
      aa_[q] = static_cast<float>(a * a);
      ab_[q] = static_cast<float>(a * b);
      bb_[q] = static_cast<float>(b * b);
      aaa_[q] = static_cast<float>(a * a * a);
      aab_[q] = static_cast<float>(a * a * b);
      abb_[q] = static_cast<float>(a * b * b);
      bbb_[q] = static_cast<float>(b * b * b);
    }
  ang_cos_.resize(static_cast<std::size_t>(Sp) * S);
  ang_sin_.resize(ang_cos_.size());
  for (int m = 0; m < Sp; ++m)
    for (int k = 0; k < S; ++k) {
      ang_cos_[m * S + k] = static_cast<float>(std::cos(-2.0 * kPi * m * k / S));
      ang_sin_[m * S + k] = static_cast<float>(std::sin(-2.0 * kPi * m * k / S));
    }
  rad_cos_.resize(static_cast<std::size_t>(Rp) * R);
  rad_sin_.resize(rad_cos_.size());
  for (int f = 0; f < Rp; ++f)
    for (int l = 0; l < R; ++l) {
      rad_cos_[f * R + l] = static_cast<float>(std::cos(-2.0 * kPi * f * l / R));
      rad_sin_[f * R + l] = static_cast<float>(std::sin(-2.0 * kPi * f * l / R));
    }
}

std::vector<float> DiscSignature::tables() const {
  std::vector<float> t;
  for (const auto* v : {&a_, &b_, &aa_, &ab_, &bb_, &aaa_, &aab_, &abb_, &bbb_, &ang_cos_,
                        &ang_sin_, &rad_cos_, &rad_sin_})
    t.insert(t.end(), v->begin(), v->end());
  return t;
}

void DiscSignature::compute(const PointCloudSequence::Cloud& pts, const int* idx, int count,
                            const Eigen::Vector3f& p, const Eigen::Vector3f& n,
                            const Eigen::Vector3f& u, double radius, float* out,
                            std::vector<std::complex<double>>& scratch) const {
  const int R = layout_.radial, S = layout_.angular;
  const int Rp = layout_.radial_freqs, Sp = layout_.angular_freqs;
  const int D = Rp * Sp;
  const int Q = R * S;
  std::fill(out, out + D, 0.0f);
  const Eigen::Vector3f v = n.cross(u);
  const double inv_rho = 1.0 / radius;

  // Scratch (no per-point allocation): 6 doubles per disc point for the fit, then in float Q
  // samples, 2 R S' ring coefficients and Q squared denominators.
  const std::size_t need_bytes = sizeof(double) * 6 * static_cast<std::size_t>(count) +
                                 sizeof(float) * (2 * static_cast<std::size_t>(Q) + 2 * R * Sp) + 64;
  const std::size_t need = need_bytes / sizeof(std::complex<double>) + 1;
  if (scratch.size() < need) scratch.resize(need);
  double* buf = reinterpret_cast<double*>(scratch.data());
  double* A = buf;
  double* B = A + count;
  double* Z = B + count;
  double* W = Z + count;
  double* GA = W + count;
  double* GB = GA + count;
  const double nan = std::numeric_limits<double>::quiet_NaN();
  int m = 0;
  for (int i = 0; i < count; ++i) {
    const Eigen::Vector3f d = pts[idx[i]].getVector3fMap() - p;
    const double a = d.dot(u) * inv_rho, b = d.dot(v) * inv_rho;
    const double r2 = a * a + b * b;
    if (r2 > 1.0) continue;
    A[m] = a;
    B[m] = b;
    Z[m] = d.dot(n) * inv_rho;
    W[m] = std::exp(-2.0 * r2);
    const Eigen::Vector3f nq = pts[idx[i]].getNormalVector3fMap();
    const double nn = nq.dot(n);
    if (nn > 0.3) {
      GA[m] = -nq.dot(u) / nn;
      GB[m] = -nq.dot(v) / nn;
    } else {
      GA[m] = GB[m] = nan;
    }
    ++m;
  }
  Eigen::Matrix<double, 10, 1> c;
  bool ok = false;
  if (m >= 16) ok = fitHeight<10>(A, B, Z, GA, GB, W, m, c);
  if (!ok && m >= 8) ok = fitHeight<6>(A, B, Z, GA, GB, W, m, c);
  if (!ok && m >= 3) ok = fitHeight<3>(A, B, Z, GA, GB, W, m, c);
  if (!ok) return;

  float cf[10];
  for (int i = 0; i < 10; ++i) cf[i] = static_cast<float>(c(i));
  float* s = reinterpret_cast<float*>(GB + count);  // Q samples, direction major
  float* re = s + Q;                               // S' x R angular coefficients
  float* im = re + R * Sp;
  float* den2 = im + R * Sp;
  sampleNormals(cf, Q, a_.data(), b_.data(), aa_.data(), ab_.data(), bb_.data(), aaa_.data(),
                aab_.data(), abb_.data(), bbb_.data(), den2, s);
  // DFT along the angle, all rings at once (contiguous in l).
  for (int f = 0; f < Sp; ++f) {
    float* rf = re + f * R;
    float* jf = im + f * R;
    std::fill(rf, rf + R, 0.0f);
    std::fill(jf, jf + R, 0.0f);
    for (int k = 0; k < S; ++k) {
      const float co = ang_cos_[f * S + k], si = ang_sin_[f * S + k];
      const float* sk = s + k * R;
      for (int l = 0; l < R; ++l) {
        rf[l] += co * sk[l];
        jf[l] += si * sk[l];
      }
    }
  }
  // DFT along the radius of the kept frequencies.
  const double norm = 1.0 / (static_cast<double>(R) * S);
  for (int fr = 0; fr < Rp; ++fr) {
    const float* tc = rad_cos_.data() + fr * R;
    const float* ts = rad_sin_.data() + fr * R;
    for (int f = 0; f < Sp; ++f) {
      const float* rf = re + f * R;
      const float* jf = im + f * R;
      double acc_re = 0.0, acc_im = 0.0;
      for (int l = 0; l < R; ++l) {
        acc_re += rf[l] * tc[l] - jf[l] * ts[l];
        acc_im += rf[l] * ts[l] + jf[l] * tc[l];
      }
      out[fr * Sp + f] = static_cast<float>(std::sqrt(acc_re * acc_re + acc_im * acc_im) * norm);
    }
  }
}

void SignatureEstimation::compute(Eigen::MatrixXf& signatures) const {
  if (!input_) throw Error("SignatureEstimation: no input cloud set");
  if (!(h_ > 0.0) || !std::isfinite(h_))
    throw Error("signature: the scale h must be positive (got " + std::to_string(h_) + ")");
  if (max_fit_points_ < 16) throw Error("signature: at least 16 fit points are needed");
  const DiscSignature disc(layout_);
  const Cloud& cloud = *input_;
  const std::size_t n = cloud.size();
  const int D = layout_.dimension();
  const double rho = 2.0 * h_;
  std::shared_ptr<const Neighbourhoods> nb = neighbourhoods_;
  if (!nb || nb->points() != n || nb->radius < static_cast<float>(rho) * 0.9999f)
    nb = std::make_shared<Neighbourhoods>(radiusNeighbourhoods(cloud, static_cast<float>(rho)));
  for (const auto& pt : cloud.points)
    if (!pt.getVector3fMap().allFinite() || !pt.getNormalVector3fMap().allFinite() ||
        pt.getNormalVector3fMap().squaredNorm() < 0.25f)
      throw Error("signature: every point needs a finite position and a unit normal (compute "
                  "the scale space first, it repairs missing normals)");

  // Row-major scratch output so that each thread writes contiguous floats.
  Eigen::Matrix<float, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> sig(n, D);
  const int maxfit = max_fit_points_;
#pragma omp parallel
  {
    std::vector<std::complex<double>> scratch;
    std::vector<int> sel;
    sel.reserve(maxfit);
#pragma omp for schedule(dynamic, 256)
    for (long jl = 0; jl < static_cast<long>(n); ++jl) {
      const std::size_t j = static_cast<std::size_t>(jl);
      const int cnt = nb->countWithin(j, static_cast<float>(rho));
      const int* row = nb->row(j);
      const int* use = row;
      int m = cnt;
      if (cnt > maxfit) {
        // Even thinning over the distance-sorted row keeps the radial distribution.
        sel.clear();
        for (int t = 0; t < maxfit; ++t)
          sel.push_back(row[static_cast<long>(t) * cnt / maxfit]);
        use = sel.data();
        m = maxfit;
      }
      const Eigen::Vector3f p = cloud[j].getVector3fMap();
      const Eigen::Vector3f nn = cloud[j].getNormalVector3fMap().normalized();
      disc.compute(cloud, use, m, p, nn, defaultTangent(nn), rho, sig.row(jl).data(), scratch);
    }
  }
  signatures = sig;
}

pcl::PCLPointCloud2 signatureCloud(const PointCloudSequence::Cloud& cloud,
                                   const Eigen::MatrixXf& signatures,
                                   const std::vector<int>& keypoints) {
  const std::size_t n = cloud.size();
  if (static_cast<std::size_t>(signatures.rows()) != n)
    throw Error("signature cloud: " + std::to_string(signatures.rows()) + " signatures for " +
                std::to_string(n) + " points");
  const int D = static_cast<int>(signatures.cols());
  pcl::PCLPointCloud2 out;
  auto field = [](const std::string& name, std::uint32_t offset, std::uint8_t type,
                  std::uint32_t count) {
    pcl::PCLPointField f;
    f.name = name;
    f.offset = offset;
    f.datatype = type;
    f.count = count;
    return f;
  };
  out.fields.push_back(field("x", 0, pcl::PCLPointField::FLOAT32, 1));
  out.fields.push_back(field("y", 4, pcl::PCLPointField::FLOAT32, 1));
  out.fields.push_back(field("z", 8, pcl::PCLPointField::FLOAT32, 1));
  out.fields.push_back(
      field("signature", 12, pcl::PCLPointField::FLOAT32, static_cast<std::uint32_t>(D)));
  out.fields.push_back(field("keypoint", 12 + 4 * D, pcl::PCLPointField::INT32, 1));
  out.point_step = 16 + 4 * D;
  out.width = static_cast<std::uint32_t>(n);
  out.height = 1;
  out.row_step = out.point_step * out.width;
  out.is_dense = true;
  out.data.assign(static_cast<std::size_t>(out.row_step), 0);
  std::vector<std::int32_t> flag(n, 0);
  for (int k : keypoints)
    if (k >= 0 && static_cast<std::size_t>(k) < n) flag[k] = 1;
  for (std::size_t j = 0; j < n; ++j) {
    std::uint8_t* dst = out.data.data() + j * out.point_step;
    std::memcpy(dst, cloud[j].data, 12);
    for (int d = 0; d < D; ++d) {
      const float v = signatures(static_cast<Eigen::Index>(j), d);
      std::memcpy(dst + 12 + 4 * d, &v, 4);
    }
    std::memcpy(dst + 12 + 4 * D, &flag[j], 4);
  }
  return out;
}

pcl::PointCloud<PointSignature24> signatureCloud24(const PointCloudSequence::Cloud& cloud,
                                                   const Eigen::MatrixXf& signatures,
                                                   const std::vector<int>& keypoints) {
  if (signatures.cols() != 24 || static_cast<std::size_t>(signatures.rows()) != cloud.size())
    throw Error("signatureCloud24 needs one 24-D signature per point");
  pcl::PointCloud<PointSignature24> out;
  out.resize(cloud.size());
  for (std::size_t j = 0; j < cloud.size(); ++j) {
    out[j].getVector3fMap() = cloud[j].getVector3fMap();
    out[j].data[3] = 1.0f;
    for (int d = 0; d < 24; ++d) out[j].signature[d] = signatures(static_cast<Eigen::Index>(j), d);
    out[j].keypoint = 0;
  }
  for (int k : keypoints)
    if (k >= 0 && static_cast<std::size_t>(k) < cloud.size()) out[k].keypoint = 1;
  return out;
}

}  // namespace pcl_animseg
