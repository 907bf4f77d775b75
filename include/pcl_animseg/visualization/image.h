#pragma once
/** \file image.h An 8-bit RGB raster and its PNG file form (libpng), for headless pictures. */
#include <cstdint>
#include <string>
#include <vector>

namespace pcl_animseg {
namespace visualization {

/** \brief A row-major 8-bit RGB image (3 bytes per pixel, no padding). */
struct RGBImage {
  int width = 0;
  int height = 0;
  std::vector<std::uint8_t> pixels;  ///< width * height * 3

  RGBImage() = default;
  /** \brief A width x height image filled with one colour. */
  RGBImage(int width, int height, std::uint8_t r = 255, std::uint8_t g = 255, std::uint8_t b = 255);

  std::uint8_t* at(int x, int y) { return &pixels[(static_cast<std::size_t>(y) * width + x) * 3]; }
  const std::uint8_t* at(int x, int y) const {
    return &pixels[(static_cast<std::size_t>(y) * width + x) * 3];
  }
  bool inside(int x, int y) const { return x >= 0 && y >= 0 && x < width && y < height; }
  /** \brief Fills the rectangle [x0, x1) x [y0, y1), clipped to the image. */
  void fillRect(int x0, int y0, int x1, int y1, std::uint8_t r, std::uint8_t g, std::uint8_t b);
};

/** \brief Writes `image` as an 8-bit RGB PNG, atomically (temp file + rename). Throws Error when
 * the image is empty or the file cannot be written. */
void writePNG(const std::string& path, const RGBImage& image);

/** \brief Reads any PNG libpng understands, converted to 8-bit RGB (alpha composited on white is
 * not done: alpha is dropped). Throws Error when the file is missing or not a PNG. */
RGBImage readPNG(const std::string& path);

/** \brief Draws `text` with the built-in 5x8 bitmap font (ASCII 32..126; other bytes as '?'),
 * each font pixel a `scale` x `scale` block, top-left corner at (x, y). Returns the x after the
 * last glyph. */
int drawText(RGBImage& image, int x, int y, const std::string& text, int scale, std::uint8_t r,
             std::uint8_t g, std::uint8_t b);

/** \brief Width in pixels of `text` drawn by drawText at `scale`. */
int textWidth(const std::string& text, int scale);
/** \brief Height in pixels of a line drawn by drawText at `scale` (descenders included). */
int textHeight(int scale);

}  // namespace visualization
}  // namespace pcl_animseg
