#pragma once
/** \file normals.h Normals for loaded frames: area-weighted mesh normals and consistently
 * oriented estimated normals for point frames (free functions, testable alone). */
#include <pcl_animseg/sequence.h>

#include <vector>

namespace pcl_animseg {
namespace io {

/** \brief Sets the normal of every vertex that lies in a non-degenerate face to the sum of its
 * faces' normals weighted by face area (the cross product of two edges), normalised.
 *
 * Faces are polygons (indices into `cloud`), fan-triangulated. When the mesh is closed (every
 * edge shared by exactly two faces) and its signed volume is negative (the winding is inward),
 * all these normals are flipped so that they point outward. Returns, per vertex, whether it got a
 * normal (vertices in no face, or only in degenerate faces, get none and keep theirs). */
std::vector<char> computeMeshNormals(PointCloudSequence::Cloud& cloud,
                                     const std::vector<pcl::Vertices>& faces);

/** \brief Estimates the normals of the points whose `known[i]` is 0 (PCA over the `k` nearest
 * neighbours among all points, the point itself included: pcl::NormalEstimation's
 * computeMeanAndCovarianceMatrix + solvePlaneParameters, in OpenMP) and orients them as
 * orientNormals() does. One kNN search serves both steps (this halves the cost of a frame
 * compared with pcl::NormalEstimationOMP followed by a separate orientation search). Points with
 * `known[i]` != 0 keep their normal and serve as orientation seeds. `known` may be empty (no point
 * known). */
void estimateNormals(PointCloudSequence::Cloud& cloud, int k, const std::vector<char>& known);

/** \brief Orients normals consistently (Hoppe et al. 1992): within each connected component of
 * the symmetric k-nearest-neighbour graph, the orientation is propagated along a minimum spanning
 * tree with edge cost 1 - |a_ij| (so it crosses flat regions first, sharp creases last), where
 * a_ij = n_i . n_j - 2 (e . n_i)(e . n_j) compares n_i with n_j mirrored across the plane midway
 * between the points (e: the unit step from i to j), and n_j is flipped when a_ij < 0. Unlike
 * Hoppe's n_i . n_j it is exact on spheres of any radius and right across a thin part, where a
 * point's neighbours include the far side (whose outward normal points the other way): with the
 * plain dot product a thin slab came out half inwards, and plain point clouds of generated
 * bodies had 2-7% of their normals flipped (a hand's fingers, an arm against the torso).
 *
 * The tree decides each sign by one edge, and where two sheets lie closer than the spacing (an
 * arm against the torso) one misleading edge turned a whole arm inside out (8-11% of a frame).
 * So the edges then vote (each point's 8 nearest): for each tree edge, the agreements a_ij of
 * the edges across the cut it makes are summed, and the subtrees with the most negative sums
 * are flipped, again until no sum is negative (at most 64 rounds per component). On a
 * generated humanoid's plain point clouds this took the flipped normals from 2.4% to 0.3%; it
 * adds about 4% to the loading of a 1M-point frame.
 *
 * - A component that contains points with `fixed[i]` != 0 is grown from all of them at once;
 *   fixed normals are never flipped.
 * - Otherwise the seed is the point farthest from the component's centroid c, oriented away from
 *   c; after propagation the whole component is flipped when the majority points inwards
 *   (mean of (p - c) . n < 0). For a closed surface this gives outward normals. For an open
 *   surface "outward" is not defined: the normals come out consistent within the component and
 *   point, on average, away from its centroid (the convex side of a cap or bowl, e.g. towards the
 *   sensor for a single-view scan of a convex object); for a flat patch the side is arbitrary
 *   (but deterministic). */
void orientNormals(PointCloudSequence::Cloud& cloud, int k, const std::vector<char>& fixed = {});

}  // namespace io
}  // namespace pcl_animseg
