// A tiny 8-bit RGB drawing surface for the figures (difference maps, colour bars, plots):
// rectangles, lines, markers and text in a built-in 5x7 bitmap font (digits, A-Z - lower case
// is drawn as upper case - and . , - + = : % ( ) / | ? space), so no font library is needed.
#pragma once

#include <array>
#include <cstdint>
#include <string>

#include "core/io/png.h"

namespace decima {

using Rgb8 = std::array<uint8_t, 3>;

class Canvas {
 public:
  Canvas(int width, int height, Rgb8 fill);

  int width() const { return image_.width; }
  int height() const { return image_.height; }
  const Image& image() const { return image_; }
  Image Take() { return std::move(image_); }

  // All drawing clips to the canvas.
  void Set(int x, int y, Rgb8 c);
  void FillRect(int x, int y, int w, int h, Rgb8 c);
  void StrokeRect(int x, int y, int w, int h, Rgb8 c);
  // Line of the given thickness (pixels) between pixel centres.
  void Line(double x0, double y0, double x1, double y1, Rgb8 c, int thickness = 1);
  // Copies `src` (RGB) with its top-left corner at (x, y).
  void Blit(const Image& src, int x, int y);
  // Text with its top-left corner at (x, y); glyphs are 5x7 cells scaled by `scale`, advance
  // 6 * scale. Returns the width drawn.
  int Text(int x, int y, const std::string& text, Rgb8 c, int scale = 1);
  static int TextWidth(const std::string& text, int scale = 1);
  static int TextHeight(int scale = 1) { return 7 * scale; }

 private:
  Image image_;
};

// Colour of t in [0, 1] on a black - purple - red - orange - pale yellow heat scale
// (monotonic in brightness, readable in greyscale).
Rgb8 HeatColor(double t);

// Short label for a tick or range value: 4 significant digits below 10,000, else 3 with a
// K or M suffix ("0", "2.5", "37.21", "1234", "120K", "2.1M").
std::string FormatNumber(double v);

}  // namespace decima
