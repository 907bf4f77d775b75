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

/** \brief The frame paths of a sequence: the frame files of a directory in natural order, or the
 * non-empty, non-comment (#) lines of a list file (relative paths are taken relative to the list
 * file's directory). Throws Error when there are none or the path does not exist. */
std::vector<std::string> listSequence(const std::string& path);

/** \brief Loads one frame. Mesh frames (OBJ, OFF, PLY with faces) give their vertices with
 * area-weighted face normals; point frames their points, with the file's normals or normals
 * estimated with PCL and oriented consistently (see sequence_io.cpp). NaN/Inf points are dropped
 * and recorded in the frame's input index. */
void loadFrame(const std::string& path, PointCloudSequence& sequence,
               const LoadOptions& options = LoadOptions());

/** \brief Loads a whole sequence (`path` as in listSequence) and checks it (point counts, units). */
PointCloudSequence loadSequence(const std::string& path, const LoadOptions& options = LoadOptions(),
                                Progress* progress = nullptr);

/** \brief The stem of a path ("dir/f01.ply" -> "f01"). */
std::string stem(const std::string& path);

/** \brief Binary PCD with x y z normal_x normal_y normal_z label (pcl::PointXYZRGBNormal-free,
 * so pcl_viewer's label handler shows it). Points whose label is < 0 get label 0 only when
 * `keep_unlabelled`, otherwise they are written with their label cast to uint32 max. Atomic. */
void saveLabelledPCD(const std::string& path, const PointCloudSequence::Cloud& cloud,
                     const std::vector<int>& labels);

/** \brief Binary little-endian PLY with x y z nx ny nz red green blue label (colour from
 * labelColor) for CloudCompare. Atomic. */
void saveLabelledPLY(const std::string& path, const PointCloudSequence::Cloud& cloud,
                     const std::vector<int>& labels);

/** \brief A stable, well separated colour per label (-1 is grey). */
void labelColor(int label, unsigned char& r, unsigned char& g, unsigned char& b);

/** \brief Writes `NAME.labels`: one line per input point, the columns being the levels
 * (columns[level][point]). All columns must have the same length. Atomic. */
void saveLabels(const std::string& path, const std::vector<std::vector<int>>& columns);

/** \brief Reads a labels / ground-truth file: rows of whitespace-separated integers; returns the
 * column `column` (0 = first). Throws Error on a malformed file. */
std::vector<int> loadLabels(const std::string& path, int column = 0);

/** \brief Reads all columns of a labels file (columns[level][point]). */
std::vector<std::vector<int>> loadLabelColumns(const std::string& path);

/** \brief Writes a frame as PLY (binary little-endian) with normals, and the faces when given;
 * used by animseg_synth and the tests. Atomic. */
void savePLY(const std::string& path, const PointCloudSequence::Cloud& cloud,
             const std::vector<pcl::Vertices>& faces = {}, bool binary = true);

}  // namespace io
}  // namespace pcl_animseg
