#pragma once
/** \file sequence_io.h Reading sequences (directory or list file) and writing labelled frames. */
#include <pcl_animseg/sequence.h>

#include <string>
#include <vector>

namespace pcl_animseg {
class Progress;
namespace io {

/** \brief Knobs for loading a sequence. */
struct LoadOptions {
  /** Frames with fewer valid points are rejected (the stages need neighbourhoods). */
  std::size_t min_points = 10;
  /** Neighbours for normal estimation of point frames without normals. */
  int normal_k = 16;
  /** Frames whose bounding-box diagonals differ by more than this factor are rejected as mixed
   * units (e.g. one frame in millimetres, the next in metres). 0 disables the check. */
  double max_scale_ratio = 20.0;
};

/** \brief True when `a` sorts before `b` in natural order ("f2" < "f10"). */
bool naturalLess(const std::string& a, const std::string& b);

/** \brief Frame extensions we read: .obj .ply .off .pcd .xyz (case-insensitive). */
bool isFrameFile(const std::string& path);

/** \brief The frame paths of a sequence: the frame files of a directory in natural order (hidden
 * files, e.g. temporaries of atomic writes, are skipped), or the non-empty, non-comment (#) lines
 * of a list file in list order (relative paths are taken relative to the list file's directory).
 * A path that is itself a frame file is a one-frame sequence. Throws Error when the path does not
 * exist, a directory has no frame files, or a list names none or names a missing file. */
std::vector<std::string> listSequence(const std::string& path);

/** \brief Loads one frame (formats: frame_readers.h) and appends it to `sequence`, named by the
 * file's stem, with the path as source.
 *
 * Mesh frames (OBJ, OFF, PLY with faces) give their vertices with area-weighted face normals
 * (computeMeshNormals in normals.h; a closed mesh wound inwards is turned outwards) and keep their
 * triangles; normals a mesh file carries are ignored for vertices in faces. Point frames give
 * their points with the file's normals (normalised) where it has them; the other points get
 * normals from a PCA over the options.normal_k nearest neighbours, oriented consistently by
 * estimateNormals / orientNormals (normals.h: Hoppe's MST propagation, outward for closed
 * surfaces; for open surfaces see there). Mesh vertices in no face are estimated the same way,
 * oriented from the mesh normals around them.
 *
 * Points with NaN/Inf coordinates are dropped (with the faces that use them) and recorded in the
 * frame's input index, so outputs can be written in input order (toInputOrder).
 *
 * Throws Error, naming the file and the problem, for a missing, unreadable, truncated or
 * malformed file, an unknown extension, or fewer than options.min_points valid points. */
void loadFrame(const std::string& path, PointCloudSequence& sequence,
               const LoadOptions& options = LoadOptions());

/** \brief Loads a whole sequence (`path` as in listSequence).
 *
 * Frames may mix formats (e.g. f1.ply, f2.obj) and point counts. Frames load in parallel (OpenMP)
 * when there are at least as many frames as threads. Progress is reported as stage "load" (one
 * unit per frame) when `progress` is given. A frame that fails fails the whole load: the Error
 * names the frame's index and path. Frames whose bounding-box diagonals differ by more than
 * options.max_scale_ratio are rejected as mixed units, naming the largest and smallest frame. */
PointCloudSequence loadSequence(const std::string& path, const LoadOptions& options = LoadOptions(),
                                Progress* progress = nullptr);

/** \brief The stem of a path ("dir/f01.ply" -> "f01"). */
std::string stem(const std::string& path);

/** \brief Binary PCD with exactly the fields x y z normal_x normal_y normal_z (float) and label
 * (uint32), so pcl_viewer offers its label colour handler. A label < 0 (unlabelled) is written as
 * its uint32 bit pattern (-1 -> 0xFFFFFFFF): pcl_viewer shows it as one more label, and it reads
 * back as -1 through a cast to int. `labels.size()` must equal `cloud.size()`. Atomic. */
void saveLabelledPCD(const std::string& path, const PointCloudSequence::Cloud& cloud,
                     const std::vector<int>& labels);

/** \brief Binary little-endian PLY with x y z nx ny nz (float), red green blue (uchar, from
 * labelColor; unlabelled points grey) and label (int, -1 for unlabelled) for CloudCompare.
 * Atomic. */
void saveLabelledPLY(const std::string& path, const PointCloudSequence::Cloud& cloud,
                     const std::vector<int>& labels);

/** \brief A stable, well separated colour per label: hue steps by the golden ratio (consecutive
 * labels far apart), saturation and value cycle; any label < 0 is grey (128, 128, 128). */
void labelColor(int label, unsigned char& r, unsigned char& g, unsigned char& b);

/** \brief Writes `NAME.labels`: one line per input point, the columns being the levels
 * (columns[level][point]). All columns must have the same length. Atomic. */
void saveLabels(const std::string& path, const std::vector<std::vector<int>>& columns);

/** \brief Reads a labels / ground-truth file: rows of whitespace-separated integers, one row per
 * point (lines starting with # are comments; trailing empty lines are ignored, an empty line in
 * between is an error); returns the column `column` (0 = first), empty for an empty file. Throws
 * Error on a malformed file, rows of different lengths, or a missing column. */
std::vector<int> loadLabels(const std::string& path, int column = 0);

/** \brief Reads all columns of a labels file (columns[level][point]). */
std::vector<std::vector<int>> loadLabelColumns(const std::string& path);

/** \brief Writes a frame as PLY (binary little-endian) with normals, and the faces when given;
 * used by animseg_synth and the tests. Atomic. */
void savePLY(const std::string& path, const PointCloudSequence::Cloud& cloud,
             const std::vector<pcl::Vertices>& faces = {}, bool binary = true);

}  // namespace io
}  // namespace pcl_animseg
