#pragma once
/** \file sequence_viewer.h Interactive viewer of a labelled sequence
 * (pcl::visualization::PCLVisualizer). PCL's headers stay in the .cpp, so including this costs
 * nothing. Its code is in the library `pcl_animseg::viewer` (PCL's visualization library and VTK's
 * rendering come with it), apart from the headless contact sheets of `pcl_animseg::visualization`.
 */
#include <pcl_animseg/visualization/labelled_sequence.h>

namespace pcl_animseg {
namespace visualization {

/** \brief Knobs of the interactive viewer. */
struct ViewerOptions {
  int level = 0;            ///< hierarchy level shown first
  double fps = 4.0;         ///< autoplay speed (frames per second)
  double point_size = 3.0;  ///< rendered point size in pixels
  bool keypoints = true;    ///< overlay keypoints (spheres of radius = scale) when the OUT has them
  std::size_t max_legend_entries = 32;
};

/** \brief True when a window can be opened (an X display is set; Debian's VTK is X11-only). */
bool displayAvailable();

/** \brief Opens a window on `sequence` and returns when it is closed. Keys: n / p next / previous
 * frame, space autoplay on/off, 0-9 level, + / - next / previous level, k keypoints on/off
 * (PCL's own keys still work: r resets the camera, q quits; PCL also binds + / - to point size).
 * Part colours are io::labelColor, so a label has the same colour in every frame and level and in
 * the contact sheet. Throws Error when the sequence is empty or no display is available. */
void runSequenceViewer(const LabelledSequence& sequence, const ViewerOptions& options);

}  // namespace visualization
}  // namespace pcl_animseg
