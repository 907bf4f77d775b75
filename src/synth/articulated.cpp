#include <pcl_animseg/error.h>
#include <pcl_animseg/io/atomic_file.h>
#include <pcl_animseg/io/sequence_io.h>
#include <pcl_animseg/progress.h>
#include <pcl_animseg/synth/articulated.h>

#include <Eigen/Geometry>
#include <algorithm>
#include <array>
#include <cctype>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <random>

namespace pcl_animseg {
namespace synth {

namespace {

constexpr double kPi = 3.14159265358979323846;
constexpr double kTwoPi = 2.0 * kPi;

double deg(double d) { return d * kPi / 180.0; }

/** \brief Random numbers that are the same on every platform: std::mt19937's output sequence is
 * fixed by the standard, but std::uniform_real_distribution / std::normal_distribution are not
 * (libstdc++ and libc++ differ), so the distributions are ours. */
class Rng {
 public:
  explicit Rng(std::initializer_list<std::uint32_t> seeds) {
    std::seed_seq seq(seeds);
    gen_.seed(seq);
  }
  /** Uniform in [0, 1) with 53 random bits. */
  double uniform() {
    const std::uint64_t hi = gen_() >> 5;  // 27 bits
    const std::uint64_t lo = gen_() >> 6;  // 26 bits
    return static_cast<double>((hi << 26) | lo) * (1.0 / 9007199254740992.0);
  }
  double uniform(double lo, double hi) { return lo + (hi - lo) * uniform(); }
  /** Standard normal (Box-Muller). */
  double normal() {
    if (has_spare_) {
      has_spare_ = false;
      return spare_;
    }
    const double u1 = 1.0 - uniform();  // (0, 1]: log is finite
    const double u2 = uniform();
    const double r = std::sqrt(-2.0 * std::log(u1));
    spare_ = r * std::sin(kTwoPi * u2);
    has_spare_ = true;
    return r * std::cos(kTwoPi * u2);
  }
  /** Uniform direction on the unit sphere (Archimedes: z uniform in [-1, 1]). */
  Eigen::Vector3d direction() {
    const double z = uniform(-1.0, 1.0);
    const double phi = kTwoPi * uniform();
    const double s = std::sqrt(std::max(0.0, 1.0 - z * z));
    return Eigen::Vector3d(s * std::cos(phi), s * std::sin(phi), z);
  }

 private:
  std::mt19937 gen_;
  bool has_spare_ = false;
  double spare_ = 0.0;
};

/** \brief One rotational degree of freedom of a joint: angle(s) = offset + amp * wave(s) with
 * s = t / T, so the motion is periodic over the sequence (smooth, loops from the last frame to
 * the first). One-sided joints (knees, elbows, finger flexion) bend one way only. */
struct Dof {
  Eigen::Vector3d axis;
  double amp_deg = 0.0;
  double phase = 0.0;  ///< in cycles
  double offset_deg = 0.0;
  bool one_sided = false;

  double angle(double s, double motion) const {
    const double w = std::sin(kTwoPi * (s + phase));
    const double a = amp_deg * motion * (one_sided ? 0.5 + 0.5 * w : w);
    return deg(offset_deg + a);
  }
};

/** \brief A part's surface in its own frame (origin at its joint). */
struct Shape {
  enum Kind { kCapsule, kEllipsoid } kind = kEllipsoid;
  Eigen::Vector3d a = Eigen::Vector3d::Zero(), b = Eigen::Vector3d::Zero();  ///< capsule axis
  double radius = 0.0;
  Eigen::Vector3d centre = Eigen::Vector3d::Zero(), semi = Eigen::Vector3d::Ones();  ///< ellipsoid

  Eigen::Vector3d centroid() const {
    return kind == kCapsule ? Eigen::Vector3d(0.5 * (a + b)) : centre;
  }

  double area() const {
    if (kind == kCapsule) return kTwoPi * radius * (b - a).norm() + 4.0 * kPi * radius * radius;
    // Knud Thomsen's approximation (relative error < 1.1%): only used to share points among
    // parts, where that error is invisible.
    const double p = 1.6075;
    const double ap = std::pow(semi.x(), p), bp = std::pow(semi.y(), p), cp = std::pow(semi.z(), p);
    return 4.0 * kPi * std::pow((ap * bp + ap * cp + bp * cp) / 3.0, 1.0 / p);
  }

  /** True when `q` (in this part's frame) lies strictly inside the solid. */
  bool inside(const Eigen::Vector3d& q) const {
    // The margin keeps points of a part from being removed by a coincident neighbour surface.
    constexpr double kMargin = 1e-9;
    if (kind == kEllipsoid) return (q - centre).cwiseQuotient(semi).squaredNorm() < 1.0 - kMargin;
    const Eigen::Vector3d ab = b - a;
    const double len2 = ab.squaredNorm();
    const double s = len2 > 0.0 ? std::clamp((q - a).dot(ab) / len2, 0.0, 1.0) : 0.0;
    return (q - (a + s * ab)).squaredNorm() < radius * radius * (1.0 - kMargin);
  }

  /** A point uniformly distributed over the surface (by area), with its outward normal. */
  void sample(Rng& rng, Eigen::Vector3d& p, Eigen::Vector3d& n) const {
    if (kind == kCapsule) {
      const Eigen::Vector3d ab = b - a;
      const double len = ab.norm();
      const double cyl = kTwoPi * radius * len;
      const double sph = 4.0 * kPi * radius * radius;
      if (rng.uniform() * (cyl + sph) < cyl) {
        Eigen::Vector3d e1, e2;
        frame(ab / len, e1, e2);
        const double h = len * rng.uniform();
        const double phi = kTwoPi * rng.uniform();
        n = std::cos(phi) * e1 + std::sin(phi) * e2;
        p = a + h * ab / len + radius * n;
      } else {
        // A uniform sphere split in two: each half lands on its own end cap, uniformly.
        n = rng.direction();
        p = (n.dot(ab) >= 0.0 ? b : a) + radius * n;
      }
      return;
    }
    // Uniform on the ellipsoid: map the unit sphere and accept with the area stretch
    // |d(ellipsoid)/d(sphere)| = |(bc x, ac y, ab z)| relative to its maximum.
    const double bc = semi.y() * semi.z(), ac = semi.x() * semi.z(), ab = semi.x() * semi.y();
    const double gmax = std::max({bc, ac, ab});
    for (;;) {
      const Eigen::Vector3d d = rng.direction();
      const double g = Eigen::Vector3d(bc * d.x(), ac * d.y(), ab * d.z()).norm();
      if (rng.uniform() * gmax <= g) {
        p = centre + semi.cwiseProduct(d);
        n = d.cwiseQuotient(semi).normalized();
        return;
      }
    }
  }

  /** Triangulated surface: rings of `res` vertices between two poles, outward-facing triangles
   * (counter-clockwise seen from outside), normals from the exact geometry. */
  void tessellate(int res, std::vector<Eigen::Vector3d>& pos, std::vector<Eigen::Vector3d>& nrm,
                  std::vector<std::array<int, 3>>& tri) const {
    struct Ring {
      double h, rad, nr, nz;
    };
    std::vector<Ring> rings;
    Eigen::Vector3d origin, e, e1, e2;
    double h_top, h_bottom;
    if (kind == kEllipsoid) {
      // A unit sphere, mapped onto the ellipsoid below.
      origin = Eigen::Vector3d::Zero();
      e1 = Eigen::Vector3d::UnitX();
      e2 = Eigen::Vector3d::UnitY();
      e = Eigen::Vector3d::UnitZ();
      const int bands = std::max(2, res / 2);
      for (int k = 1; k < bands; ++k) {
        const double th = kPi * k / bands;
        rings.push_back({std::cos(th), std::sin(th), std::sin(th), std::cos(th)});
      }
      h_top = 1.0;
      h_bottom = -1.0;
    } else {
      const Eigen::Vector3d ab = b - a;
      const double len = ab.norm();
      origin = a;
      e = ab / len;
      frame(e, e1, e2);
      const int hemi = std::max(1, res / 4);
      for (int k = 1; k <= hemi; ++k) {  // top cap, pole to equator
        const double beta = 0.5 * kPi * (1.0 - static_cast<double>(k) / hemi);
        rings.push_back({len + radius * std::sin(beta), radius * std::cos(beta), std::cos(beta),
                         std::sin(beta)});
      }
      // Cylinder rings about as far apart as the vertices around, so triangles stay well shaped.
      const int bands =
          std::clamp(static_cast<int>(std::lround(len / (kTwoPi * radius / res))), 1, res);
      for (int j = 1; j < bands; ++j)
        rings.push_back({len * (1.0 - static_cast<double>(j) / bands), radius, 1.0, 0.0});
      for (int k = 0; k < hemi; ++k) {  // bottom cap, equator to pole
        const double beta = 0.5 * kPi * static_cast<double>(k) / hemi;
        rings.push_back(
            {-radius * std::sin(beta), radius * std::cos(beta), std::cos(beta), -std::sin(beta)});
      }
      h_top = len + radius;
      h_bottom = -radius;
    }
    const int base = static_cast<int>(pos.size());
    auto add = [&](const Eigen::Vector3d& p, const Eigen::Vector3d& n) {
      if (kind == kEllipsoid) {
        pos.push_back(centre + semi.cwiseProduct(p));
        nrm.push_back(n.cwiseQuotient(semi).normalized());
      } else {
        pos.push_back(p);
        nrm.push_back(n.normalized());
      }
    };
    add(origin + h_top * e, e);
    for (const Ring& r : rings)
      for (int j = 0; j < res; ++j) {
        const double phi = kTwoPi * j / res;
        const Eigen::Vector3d radial = std::cos(phi) * e1 + std::sin(phi) * e2;
        add(origin + r.h * e + r.rad * radial, r.nr * radial + r.nz * e);
      }
    add(origin + h_bottom * e, -e);
    const int nr = static_cast<int>(rings.size());
    const int top = base, bottom = base + 1 + nr * res;
    auto v = [&](int ring, int j) { return base + 1 + ring * res + (j % res); };
    for (int j = 0; j < res; ++j) tri.push_back({top, v(0, j), v(0, j + 1)});
    for (int k = 0; k + 1 < nr; ++k)
      for (int j = 0; j < res; ++j) {
        tri.push_back({v(k, j), v(k + 1, j), v(k, j + 1)});
        tri.push_back({v(k, j + 1), v(k + 1, j), v(k + 1, j + 1)});
      }
    for (int j = 0; j < res; ++j) tri.push_back({v(nr - 1, j), bottom, v(nr - 1, j + 1)});
  }

  /** A right-handed frame (e1, e2, e): e1 x e2 = e. */
  static void frame(const Eigen::Vector3d& e, Eigen::Vector3d& e1, Eigen::Vector3d& e2) {
    const Eigen::Vector3d helper =
        std::abs(e.x()) < 0.9 ? Eigen::Vector3d::UnitX() : Eigen::Vector3d::UnitY();
    e1 = helper.cross(e).normalized();
    e2 = e.cross(e1);
  }
};

Shape capsule(const Eigen::Vector3d& a, const Eigen::Vector3d& b, double r) {
  Shape s;
  s.kind = Shape::kCapsule;
  s.a = a;
  s.b = b;
  s.radius = r;
  return s;
}

Shape ellipsoid(const Eigen::Vector3d& c, const Eigen::Vector3d& semi) {
  Shape s;
  s.kind = Shape::kEllipsoid;
  s.centre = c;
  s.semi = semi;
  return s;
}

Dof dof(const Eigen::Vector3d& axis, double amp, double phase, bool one_sided = false,
        double offset = 0.0) {
  Dof d;
  d.axis = axis.normalized();
  d.amp_deg = amp;
  d.phase = phase;
  d.one_sided = one_sided;
  d.offset_deg = offset;
  return d;
}

/** \brief A rigid part: its frame sits at `joint` in the parent's frame and turns by its dofs.
 * Parents come before children, so one pass poses the tree. */
struct Part {
  std::string name;
  int parent = -1;
  Eigen::Vector3d joint = Eigen::Vector3d::Zero();
  Shape shape;
  std::vector<Dof> dofs;
};

using Body = std::vector<Part>;
using V = Eigen::Vector3d;

int addPart(Body& body, const std::string& name, int parent, const V& joint, const Shape& shape,
            std::vector<Dof> dofs) {
  Part p;
  p.name = name;
  p.parent = parent;
  p.joint = joint;
  p.shape = shape;
  p.dofs = std::move(dofs);
  body.push_back(p);
  return static_cast<int>(body.size()) - 1;
}

// Body plans. x is forward, y left, z up. Every child's shape contains (or its capsule cap covers)
// its joint and reaches into the parent, so parts overlap at joints like a real body and stay
// attached in every pose. Angles are in degrees, phases in cycles of the sequence.
const V kX = V::UnitX(), kY = V::UnitY(), kZ = V::UnitZ();

Body quadruped() {
  Body b;
  const int torso = addPart(b, "torso", -1, V::Zero(), ellipsoid(V::Zero(), V(0.55, 0.2, 0.2)),
                            {dof(kY, 5, 0.0), dof(kX, 3, 0.25)});
  const int neck = addPart(b, "neck", torso, V(0.45, 0, 0.08),
                           capsule(V::Zero(), V(0.18, 0, 0.22), 0.08), {dof(kY, 15, 0.1)});
  addPart(b, "head", neck, V(0.18, 0, 0.22), ellipsoid(V(0.1, 0, 0.02), V(0.17, 0.09, 0.09)),
          {dof(kY, 20, 0.3), dof(kZ, 15, 0.0)});
  addPart(b, "tail", torso, V(-0.5, 0, 0.06), capsule(V::Zero(), V(-0.35, 0, 0.12), 0.045),
          {dof(kZ, 35, 0.0), dof(kY, 20, 0.25)});
  // Gallop: the front pair and the back pair each move nearly together, half a cycle apart.
  const struct {
    const char* name;
    double x, y, phase;
    bool front;
  } legs[] = {{"fl", 0.36, 0.11, 0.0, true},
              {"fr", 0.36, -0.11, 0.1, true},
              {"bl", -0.36, 0.11, 0.5, false},
              {"br", -0.36, -0.11, 0.6, false}};
  for (const auto& l : legs) {
    const int upper = addPart(b, std::string("leg_") + l.name + "_upper", torso, V(l.x, l.y, -0.1),
                              capsule(V::Zero(), V(0, 0, -0.32), 0.07), {dof(kY, 50, l.phase)});
    // Front knees fold backward, hocks forward.
    addPart(b, std::string("leg_") + l.name + "_lower", upper, V(0, 0, -0.32),
            capsule(V::Zero(), V(0, 0, -0.3), 0.05),
            {dof(kY, l.front ? 60 : -60, l.phase + 0.25, true)});
  }
  return b;
}

Body humanoid() {
  Body b;
  const int pelvis = addPart(b, "pelvis", -1, V::Zero(), ellipsoid(V::Zero(), V(0.11, 0.17, 0.1)),
                             {dof(kZ, 8, 0.0)});
  const int torso =
      addPart(b, "torso", pelvis, V(0, 0, 0.05), ellipsoid(V(0, 0, 0.27), V(0.11, 0.17, 0.25)),
              {dof(kY, 8, 0.0, false, 5), dof(kZ, 12, 0.5)});
  addPart(b, "head", torso, V(0, 0, 0.5), ellipsoid(V(0, 0, 0.11), V(0.09, 0.08, 0.12)),
          {dof(kY, 10, 0.2), dof(kZ, 20, 0.0)});
  // Arms swing against the legs of the same side; elbows bend forward (negative about y).
  for (int side = 0; side < 2; ++side) {
    const double s = side == 0 ? 1.0 : -1.0;
    const std::string tag = side == 0 ? "l" : "r";
    const double ph = side == 0 ? 0.5 : 0.0;
    const int upper = addPart(b, "arm_" + tag + "_upper", torso, V(0, 0.14 * s, 0.44),
                              capsule(V::Zero(), V(0, 0.1 * s, -0.27), 0.045),
                              {dof(kY, 45, ph), dof(kX, 10 * s, ph + 0.25, true)});
    const int fore =
        addPart(b, "arm_" + tag + "_fore", upper, V(0, 0.1 * s, -0.27),
                capsule(V::Zero(), V(0, 0.02 * s, -0.25), 0.038), {dof(kY, -60, ph + 0.25, true)});
    addPart(b, "arm_" + tag + "_hand", fore, V(0, 0.02 * s, -0.25),
            ellipsoid(V(0, 0, -0.08), V(0.035, 0.05, 0.09)), {dof(kY, 20, ph)});
  }
  for (int side = 0; side < 2; ++side) {
    const double s = side == 0 ? 1.0 : -1.0;
    const std::string tag = side == 0 ? "l" : "r";
    const double ph = side == 0 ? 0.0 : 0.5;
    const int thigh = addPart(b, "leg_" + tag + "_thigh", pelvis, V(0, 0.09 * s, -0.05),
                              capsule(V::Zero(), V(0, 0.01 * s, -0.42), 0.07), {dof(kY, 40, ph)});
    const int shin =
        addPart(b, "leg_" + tag + "_shin", thigh, V(0, 0.01 * s, -0.42),
                capsule(V::Zero(), V(0, 0, -0.4), 0.05), {dof(kY, 70, ph + 0.3, true)});
    addPart(b, "leg_" + tag + "_foot", shin, V(0, 0, -0.4),
            ellipsoid(V(0.07, 0, -0.04), V(0.12, 0.05, 0.04)), {dof(kY, 20, ph + 0.5)});
  }
  return b;
}

Body spider() {
  Body b;
  const int body = addPart(b, "body", -1, V::Zero(), ellipsoid(V::Zero(), V(0.3, 0.2, 0.12)),
                           {dof(kZ, 5, 0.0), dof(kX, 4, 0.25)});
  // Alternating tetrapod gait: legs 1 and 3 of one side move with 2 and 4 of the other.
  for (int side = 0; side < 2; ++side) {
    const double s = side == 0 ? 1.0 : -1.0;
    for (int i = 0; i < 4; ++i) {
      const double phi = s * deg(35.0 + 37.0 * i);
      const V dir(std::cos(phi), std::sin(phi), 0.0);
      const V tangent(-std::sin(phi), std::cos(phi), 0.0);  // rotating about it lowers the leg
      const double ph = ((i + side) % 2) * 0.5;
      const std::string tag = std::string(side == 0 ? "l" : "r") + std::to_string(i + 1);
      const V knee = 0.32 * dir + V(0, 0, 0.18);
      // Neighbouring legs are 37 degrees apart and swing in opposite phases: +-16 degrees each
      // keeps them apart (at +-25 they passed through each other).
      const int upper = addPart(
          b, "leg_" + tag + "_upper", body, V(0.22 * dir.x(), 0.15 * dir.y(), 0.02),
          capsule(V::Zero(), knee, 0.035), {dof(kZ, 16 * s, ph), dof(tangent, -15, ph + 0.25)});
      addPart(b, "leg_" + tag + "_lower", upper, knee,
              capsule(V::Zero(), 0.14 * dir + V(0, 0, -0.42), 0.028),
              {dof(tangent, 20, ph + 0.25)});
    }
  }
  return b;
}

Body snake() {
  Body b;
  const int n = 10;
  const double len = 0.22;
  int parent = -1;
  for (int i = 0; i < n; ++i) {
    // A travelling wave from head (segment 0) to tail; the radius tapers toward the tail.
    const double r = 0.07 - 0.0035 * i;
    parent = addPart(b, "segment_" + std::to_string(i), parent, i == 0 ? V::Zero() : V(len, 0, 0),
                     capsule(V::Zero(), V(len, 0, 0), r),
                     {dof(kZ, i == 0 ? 20 : 30, -0.1 * i), dof(kY, 6, -0.1 * i + 0.25)});
  }
  // Segment i hangs off segment i-1's far end, so the chain points along +x from the head: turn
  // it so the head leads (the parts are mirrored along x, which changes nothing else).
  for (Part& p : b) {
    p.joint.x() = -p.joint.x();
    p.shape.b.x() = -p.shape.b.x();
  }
  return b;
}

Body hand() {
  // Ten times life size, so the palm is about one unit long like the other plans' bodies.
  Body b;
  const int palm = addPart(b, "palm", -1, V::Zero(), ellipsoid(V::Zero(), V(0.5, 0.45, 0.15)),
                           {dof(kY, 15, 0.0), dof(kX, 10, 0.25)});
  const struct {
    const char* name;
    double y, base_x, size;
  } fingers[] = {{"index", 0.3, 0.35, 1.0},
                 {"middle", 0.1, 0.42, 1.1},
                 {"ring", -0.1, 0.42, 1.0},
                 {"pinky", -0.3, 0.35, 0.8}};
  const double lens[3] = {0.4, 0.26, 0.2}, radii[3] = {0.085, 0.075, 0.065};
  const char* bones[3] = {"proximal", "middle", "distal"};
  for (int k = 0; k < 4; ++k) {
    int parent = palm;
    V joint(fingers[k].base_x, fingers[k].y, 0.0);
    for (int j = 0; j < 3; ++j) {
      const double len = lens[j] * fingers[k].size;
      // Flexion about +y bends a finger toward the palm side (-z); a wave runs across fingers.
      std::vector<Dof> dofs = {dof(kY, 70, 0.08 * k + 0.1 * j, true)};
      if (j == 0) dofs.push_back(dof(kZ, 8, 0.08 * k + 0.25));
      parent = addPart(b, std::string(fingers[k].name) + "_" + bones[j], parent, joint,
                       capsule(V::Zero(), V(len, 0, 0), radii[j] * (0.9 + 0.1 * fingers[k].size)),
                       std::move(dofs));
      joint = V(len, 0, 0);
    }
  }
  const V dir(0.6, 0.8, 0.0), flex(-0.8, 0.6, 0.0);  // flex x dir = -z: toward the palm side
  const double tl[3] = {0.35, 0.28, 0.22}, tr[3] = {0.1, 0.085, 0.075};
  const char* tb[3] = {"metacarpal", "proximal", "distal"};
  int parent = palm;
  V joint(-0.05, 0.3, 0.0);
  for (int j = 0; j < 3; ++j) {
    std::vector<Dof> dofs = {dof(flex, 50, 0.5 + 0.1 * j, true)};
    if (j == 0) dofs.push_back(dof(kZ, 15, 0.75));
    parent = addPart(b, std::string("thumb_") + tb[j], parent, joint,
                     capsule(V::Zero(), tl[j] * dir, tr[j]), std::move(dofs));
    joint = tl[j] * dir;
  }
  return b;
}

Body makeBody(BodyPlan plan) {
  switch (plan) {
    case BodyPlan::Quadruped:
      return quadruped();
    case BodyPlan::Humanoid:
      return humanoid();
    case BodyPlan::Spider:
      return spider();
    case BodyPlan::Snake:
      return snake();
    case BodyPlan::Hand:
      return hand();
  }
  throw Error("unknown body plan");
}

void scaleBody(Body& body, double s) {
  for (Part& p : body) {
    p.joint *= s;
    p.shape.a *= s;
    p.shape.b *= s;
    p.shape.radius *= s;
    p.shape.centre *= s;
    p.shape.semi *= s;
  }
}

/** \brief Part-to-world transforms of the body at sequence time s in [0, 1). */
std::vector<Eigen::Isometry3d> pose(const Body& body, double s, double motion,
                                    const Eigen::Isometry3d& global) {
  std::vector<Eigen::Isometry3d> world(body.size());
  for (std::size_t i = 0; i < body.size(); ++i) {
    const Part& p = body[i];
    Eigen::Isometry3d local = Eigen::Isometry3d::Identity();
    local.translate(p.joint);
    for (const Dof& d : p.dofs) local.rotate(Eigen::AngleAxisd(d.angle(s, motion), d.axis));
    world[i] = (p.parent < 0 ? global : world[p.parent]) * local;
  }
  return world;
}

/** \brief Slow rigid motion of the whole body so that frames are not trivially aligned: a drift
 * of ~0.35 body sizes with some sway, and a yaw that turns ~35 degrees over the sequence from a
 * seed-dependent heading. */
Eigen::Isometry3d globalMotion(double s, double size, double heading) {
  Eigen::Isometry3d g = Eigen::Isometry3d::Identity();
  g.translate(size * V(0.35 * s, 0.08 * std::sin(kTwoPi * s), 0.04 * std::sin(2.0 * kTwoPi * s)));
  g.rotate(Eigen::AngleAxisd(heading + deg(35.0) * s + deg(10.0) * std::sin(kTwoPi * s), kZ));
  return g;
}

double restSize(const Body& body) {
  const auto world = pose(body, 0.0, 0.0, Eigen::Isometry3d::Identity());
  V lo = V::Constant(1e300), hi = V::Constant(-1e300);
  for (std::size_t i = 0; i < body.size(); ++i) {
    std::vector<V> pos, nrm;
    std::vector<std::array<int, 3>> tri;
    body[i].shape.tessellate(8, pos, nrm, tri);
    for (const V& p : pos) {
      const V w = world[i] * p;
      lo = lo.cwiseMin(w);
      hi = hi.cwiseMax(w);
    }
  }
  return (hi - lo).norm();
}

pcl::PointNormal makePoint(const V& p, const V& n) {
  pcl::PointNormal q;
  q.x = static_cast<float>(p.x());
  q.y = static_cast<float>(p.y());
  q.z = static_cast<float>(p.z());
  q.normal_x = static_cast<float>(n.x());
  q.normal_y = static_cast<float>(n.y());
  q.normal_z = static_cast<float>(n.z());
  q.curvature = 0.0f;
  return q;
}

double cloudDiagonal(const PointCloudSequence::Cloud& c) {
  if (c.empty()) return 0.0;
  Eigen::Vector3f lo = c[0].getVector3fMap(), hi = lo;
  for (const auto& p : c) {
    lo = lo.cwiseMin(p.getVector3fMap());
    hi = hi.cwiseMax(p.getVector3fMap());
  }
  return static_cast<double>((hi - lo).norm());
}

std::string lower(std::string s) {
  for (char& c : s) c = static_cast<char>(std::tolower(static_cast<unsigned char>(c)));
  return s;
}

}  // namespace

BodyPlan bodyPlanFromString(const std::string& name) {
  const std::string n = lower(name);
  for (BodyPlan p : allBodyPlans())
    if (toString(p) == n) return p;
  throw Error("unknown body plan '" + name +
              "' (expected quadruped, humanoid, spider, snake or hand)");
}

std::string toString(BodyPlan plan) {
  switch (plan) {
    case BodyPlan::Quadruped:
      return "quadruped";
    case BodyPlan::Humanoid:
      return "humanoid";
    case BodyPlan::Spider:
      return "spider";
    case BodyPlan::Snake:
      return "snake";
    case BodyPlan::Hand:
      return "hand";
  }
  return "unknown";
}

std::vector<BodyPlan> allBodyPlans() {
  return {BodyPlan::Quadruped, BodyPlan::Humanoid, BodyPlan::Spider, BodyPlan::Snake,
          BodyPlan::Hand};
}

int partCount(BodyPlan plan) { return static_cast<int>(makeBody(plan).size()); }

std::vector<std::string> partNames(BodyPlan plan) {
  std::vector<std::string> names;
  for (const Part& p : makeBody(plan)) names.push_back(p.name);
  return names;
}

std::string frameName(std::size_t t, std::size_t frames) {
  int digits = 3;
  for (std::size_t m = 1000; frames > m; m *= 10) ++digits;
  char buf[32];
  std::snprintf(buf, sizeof(buf), "f%0*zu", digits, t);
  return buf;
}

void validate(const SynthParams& p) {
  if (p.frames < 1)
    throw Error("synth: frames must be at least 1 (got " + std::to_string(p.frames) + ")");
  if (p.points < 10)
    throw Error("synth: points must be at least 10 (got " + std::to_string(p.points) + ")");
  if (!(p.point_variation >= 0.0 && p.point_variation < 1.0))
    throw Error("synth: point variation must be in [0, 1) (got " +
                std::to_string(p.point_variation) + ")");
  if (!(p.noise >= 0.0) || !std::isfinite(p.noise))
    throw Error("synth: noise must be a finite value >= 0 (got " + std::to_string(p.noise) + ")");
  if (!(p.motion >= 0.0) || !std::isfinite(p.motion))
    throw Error("synth: motion must be a finite value >= 0 (got " + std::to_string(p.motion) + ")");
  if (!(p.scale > 0.0) || !std::isfinite(p.scale))
    throw Error("synth: scale must be > 0 (got " + std::to_string(p.scale) + ")");
  if (p.mesh_resolution < 4 || p.mesh_resolution > 256)
    throw Error("synth: mesh resolution must be in [4, 256] (got " +
                std::to_string(p.mesh_resolution) + ")");
}

std::vector<SynthFrame> generate(const SynthParams& params) {
  validate(params);
  Body body = makeBody(params.plan);
  scaleBody(body, params.scale);
  const std::size_t parts = body.size();
  const double size = restSize(body);

  // Per-sequence choices (heading, small changes of the gait) come from their own stream; every
  // frame then has its own stream, so frames can be made in parallel with identical results.
  Rng seq_rng({params.seed, 0x5eedu});
  const double heading = kTwoPi * seq_rng.uniform();
  for (Part& p : body)
    for (Dof& d : p.dofs) {
      d.amp_deg *= 1.0 + 0.1 * seq_rng.uniform(-1.0, 1.0);
      d.phase += 0.05 * seq_rng.uniform(-1.0, 1.0);
    }

  std::vector<double> cdf(parts);
  double total_area = 0.0;
  for (std::size_t i = 0; i < parts; ++i) cdf[i] = total_area += body[i].shape.area();

  // Mesh mode: one tessellation per part, in the part's frame, reused (posed) in every frame.
  std::vector<V> mesh_pos, mesh_nrm;
  std::vector<int> mesh_part;
  std::vector<pcl::Vertices> mesh_faces;
  if (params.mesh) {
    for (std::size_t i = 0; i < parts; ++i) {
      std::vector<std::array<int, 3>> tri;
      body[i].shape.tessellate(params.mesh_resolution, mesh_pos, mesh_nrm, tri);
      mesh_part.resize(mesh_pos.size(), static_cast<int>(i));
      for (const auto& t : tri) {
        pcl::Vertices v;
        v.vertices.assign(t.begin(), t.end());
        mesh_faces.push_back(v);
      }
    }
  }

  const int frames = params.frames;
  std::vector<SynthFrame> out(frames);
  std::vector<std::string> failures(frames);
#pragma omp parallel for schedule(dynamic)
  for (int t = 0; t < frames; ++t) {
    SynthFrame& f = out[t];
    f.cloud.reset(new PointCloudSequence::Cloud);
    const double s = static_cast<double>(t) / frames;
    const auto world = pose(body, s, params.motion, globalMotion(s, size, heading));
    std::vector<Eigen::Isometry3d> inv(parts);
    for (std::size_t i = 0; i < parts; ++i) {
      inv[i] = world[i].inverse();
      f.part_centres.push_back(world[i] * body[i].shape.centroid());
    }
    Rng rng({params.seed, static_cast<std::uint32_t>(t), 0xf00du});

    if (params.mesh) {
      f.cloud->reserve(mesh_pos.size());
      for (std::size_t k = 0; k < mesh_pos.size(); ++k) {
        const Eigen::Isometry3d& w = world[mesh_part[k]];
        f.cloud->push_back(makePoint(w * mesh_pos[k], w.linear() * mesh_nrm[k]));
      }
      f.labels = mesh_part;
      f.faces = mesh_faces;
    } else {
      const double n_mean = static_cast<double>(params.points);
      const std::size_t n = static_cast<std::size_t>(std::max(
          1L, std::lround(n_mean * (1.0 + params.point_variation * rng.uniform(-1.0, 1.0)))));
      f.cloud->reserve(n);
      f.labels.reserve(n);
      // Samples inside another part are not on the union's outer surface: drop and draw again.
      const std::size_t max_tries = 100 * n + 10000;
      std::size_t tries = 0;
      while (f.labels.size() < n) {
        if (++tries > max_tries) {
          failures[t] = "synth: frame " + std::to_string(t) +
                        ": the parts hide each other's surfaces almost entirely";
          break;
        }
        const double u = rng.uniform() * total_area;
        const std::size_t i = static_cast<std::size_t>(
            std::min<std::ptrdiff_t>(std::upper_bound(cdf.begin(), cdf.end(), u) - cdf.begin(),
                                     static_cast<std::ptrdiff_t>(parts) - 1));
        V p, nl;
        body[i].shape.sample(rng, p, nl);
        const V pw = world[i] * p;
        bool hidden = false;
        for (std::size_t j = 0; j < parts && !hidden; ++j)
          hidden = j != i && body[j].shape.inside(inv[j] * pw);
        if (hidden) continue;
        f.cloud->push_back(makePoint(pw, world[i].linear() * nl));
        f.labels.push_back(static_cast<int>(i));
      }
    }
    if (params.noise > 0.0) {
      const double sigma = params.noise * cloudDiagonal(*f.cloud);
      for (auto& q : *f.cloud) {
        q.x += static_cast<float>(sigma * rng.normal());
        q.y += static_cast<float>(sigma * rng.normal());
        q.z += static_cast<float>(sigma * rng.normal());
      }
    }
    f.cloud->width = static_cast<std::uint32_t>(f.cloud->size());
    f.cloud->height = 1;
    f.cloud->is_dense = true;
  }
  for (const std::string& e : failures)
    if (!e.empty()) throw Error(e);
  return out;
}

PointCloudSequence toSequence(const std::vector<SynthFrame>& frames) {
  PointCloudSequence seq;
  for (std::size_t t = 0; t < frames.size(); ++t)
    seq.addFrame(frames[t].cloud, frameName(t, frames.size()), "", {}, 0, frames[t].faces);
  return seq;
}

void writeSequence(const std::string& dir, const std::vector<SynthFrame>& frames,
                   Progress* progress) {
  io::ensureDirectory(dir);
  for (std::size_t t = 0; t < frames.size(); ++t) {
    const std::string base = dir + "/" + frameName(t, frames.size());
    io::savePLY(base + ".ply", *frames[t].cloud, frames[t].faces, true);
    io::saveLabels(base + ".gt", {frames[t].labels});
    if (progress) progress->update(t + 1);
  }
}

}  // namespace synth
}  // namespace pcl_animseg
