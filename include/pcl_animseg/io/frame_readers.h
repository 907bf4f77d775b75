#pragma once
/** \file frame_readers.h One frame file as written on disk, before NaN removal and normals.
 *
 * loadFrame() is what most code wants; these readers are exposed for tests and for tools that
 * need the file's own content (e.g. its vertex order). */
#include <pcl/PCLPointCloud2.h>
#include <pcl/Vertices.h>

#include <Eigen/Core>
#include <string>
#include <vector>

namespace pcl_animseg {
namespace io {

/** \brief A frame file's content, in file order. */
struct RawFrame {
  /** Positions, one per input point/vertex (may contain NaN/Inf). */
  std::vector<Eigen::Vector3f> points;
  /** Empty when the file has no normals; else one per point, NaN where a point has none. */
  std::vector<Eigen::Vector3f> normals;
  /** Triangles (polygons are fan-triangulated), indices into `points`; empty for point frames. */
  std::vector<pcl::Vertices> faces;
  /** "obj", "off", "ply", "pcd" or "xyz". */
  std::string format;
};

/** \brief Wavefront OBJ: `v x y z` (extra values ignored), `f a b c ...` with `a`, `a/t`,
 * `a/t/n`, `a//n` forms and negative (relative) indices; `vn` are used only for a face-less file
 * with one `vn` per `v`. Other statements are ignored. */
RawFrame readOBJ(const std::string& path);

/** \brief Object File Format: `[ST][C][N]OFF` headers (counts may share the keyword's line),
 * `#` comments; per-vertex normals (NOFF) are read, colours skipped. 4D / nD and binary OFF are
 * rejected. */
RawFrame readOFF(const std::string& path);

/** \brief PLY (ascii, binary little or big endian), read by hand (PCL's PLY reader aborts on
 * some corrupt files): vertex x y z [nx ny nz | normal_x normal_y normal_z] of any scalar type,
 * faces from the face element's `vertex_indices` (or `vertex_index`) list; other properties and
 * elements are skipped. */
RawFrame readPLY(const std::string& path);

/** \brief Every field of a PCD file (ascii, binary or binary_compressed), read by hand after
 * a strict header check: PCL's PCD reader crashes on some corrupt files (docs/reliability.md).
 * Fields keep their declared types; throws Error on any bad file. */
pcl::PCLPointCloud2 readPCDCloud(const std::string& path);

/** \brief PCD through readPCDCloud: x y z, and normal_x normal_y normal_z when present. */
RawFrame readPCD(const std::string& path);

/** \brief Text, one point per line: `x y z` or `x y z nx ny nz` (further columns ignored; so a
 * file with 6+ columns is read as having normals), separated by spaces, tabs or commas; empty
 * lines and lines starting with `#` are skipped. */
RawFrame readXYZ(const std::string& path);

/** \brief Dispatches on the extension (case-insensitive). Throws Error for an unknown one. */
RawFrame readRawFrame(const std::string& path);

}  // namespace io
}  // namespace pcl_animseg
