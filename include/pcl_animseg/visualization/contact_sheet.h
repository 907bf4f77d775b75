#pragma once
/** \file contact_sheet.h A headless picture of a decomposition: a grid of frames evenly spread over
 * the sequence, points coloured by part, with frame names and a legend.
 *
 * The renderer is our own small software rasteriser (orthographic projection, z-buffer, shaded
 * point splats) rather than VTK: Debian's VTK is built for X11 without EGL/OSMesa, so offscreen
 * VTK rendering needs an X server, which CI machines and most compute nodes do not have. Nothing
 * here opens a window or touches OpenGL. */
#include <pcl_animseg/visualization/image.h>
#include <pcl_animseg/visualization/labelled_sequence.h>

#include <Eigen/Core>

#include <string>
#include <vector>

namespace pcl_animseg {
namespace visualization {

/** \brief Knobs of the contact sheet (`animseg_view --png`, `animseg --png`). */
struct ContactSheetOptions {
  int level = 0;            ///< hierarchy level to colour by (0 = finest)
  int frames = 0;           ///< frames shown, evenly spread; 0 = all up to 8
  int columns = 0;          ///< grid columns; 0 = all frames in one row up to 4, else two rows
  int width = 1600;         ///< picture width in pixels
  float splat_radius = 0;   ///< point splat radius in pixels; 0 = from the point spacing
  /** Direction the camera looks along (world units, need not be unit length); zero = a 3/4 view
   * from frame 0's principal axes (see defaultViewDirection). */
  Eigen::Vector3f view_direction = Eigen::Vector3f::Zero();
  /** Up direction on the picture; zero = as chosen by defaultView. */
  Eigen::Vector3f up = Eigen::Vector3f::Zero();
  std::string title;        ///< header line; empty = "<frames> frames, level L: K parts"
  bool legend = true;       ///< part ids, colours and point counts below the grid
};

/** \brief Where things went on the picture (for tests and callers that annotate it). */
struct ContactSheetLayout {
  struct Rect {
    int x0 = 0, y0 = 0, x1 = 0, y1 = 0;  ///< [x0, x1) x [y0, y1)
  };
  std::vector<std::size_t> frames;  ///< sequence index of each cell
  std::vector<Rect> cells;          ///< drawing area of each cell (below its name)
  Rect legend;                      ///< empty when there is no legend
  int parts = 0;                    ///< parts (labels >= 0) at the level, over all frames
};

/** \brief `n` frame indices evenly spread over [0, T) (first and last included when n >= 2). */
std::vector<std::size_t> spreadFrames(std::size_t T, std::size_t n);

/** \brief A 3/4 view of `cloud` from its principal axes e1 >= e2 >= e3 (each signed so that its
 * largest component is positive, for a stable choice). Up is whichever of e1, e2 lies within 30
 * degrees of world +Z, else of world +Y, else e2; with s the other broad axis, the camera looks
 * along -(e3 + 0.7 s + 0.45 up): from the side the object is thinnest in, turned and raised.
 * Override with ContactSheetOptions::up / view_direction when the data's up is elsewhere. */
void defaultView(const PointCloudSequence::Cloud& cloud, Eigen::Vector3f& view_direction,
                 Eigen::Vector3f& up);

/** \brief Renders the sheet in memory. Throws Error on an empty sequence or a level it lacks. */
RGBImage renderContactSheet(const LabelledSequence& sequence, const ContactSheetOptions& options,
                            ContactSheetLayout* layout = nullptr);

/** \brief Reads the OUT directory of `animseg` (loadLabelledSequence) and writes the sheet to
 * `png_path` (atomically). */
void renderContactSheet(const std::string& out_dir, const std::string& png_path,
                        const ContactSheetOptions& options);

}  // namespace visualization
}  // namespace pcl_animseg
