#include "core/render/canvas.h"

#include <algorithm>
#include <cctype>
#include <cmath>
#include <cstdio>

namespace decima {
namespace {

// 5x7 glyphs, one byte per row (top to bottom), bit 4 = leftmost column.
struct Glyph {
  char c;
  uint8_t rows[7];
};
constexpr Glyph kFont[] = {
    {'0', {0x0E, 0x11, 0x13, 0x15, 0x19, 0x11, 0x0E}},
    {'1', {0x04, 0x0C, 0x04, 0x04, 0x04, 0x04, 0x0E}},
    {'2', {0x0E, 0x11, 0x01, 0x02, 0x04, 0x08, 0x1F}},
    {'3', {0x1E, 0x01, 0x01, 0x0E, 0x01, 0x01, 0x1E}},
    {'4', {0x02, 0x06, 0x0A, 0x12, 0x1F, 0x02, 0x02}},
    {'5', {0x1F, 0x10, 0x1E, 0x01, 0x01, 0x11, 0x0E}},
    {'6', {0x06, 0x08, 0x10, 0x1E, 0x11, 0x11, 0x0E}},
    {'7', {0x1F, 0x01, 0x02, 0x04, 0x08, 0x08, 0x08}},
    {'8', {0x0E, 0x11, 0x11, 0x0E, 0x11, 0x11, 0x0E}},
    {'9', {0x0E, 0x11, 0x11, 0x0F, 0x01, 0x02, 0x0C}},
    {'A', {0x0E, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11}},
    {'B', {0x1E, 0x11, 0x11, 0x1E, 0x11, 0x11, 0x1E}},
    {'C', {0x0E, 0x11, 0x10, 0x10, 0x10, 0x11, 0x0E}},
    {'D', {0x1C, 0x12, 0x11, 0x11, 0x11, 0x12, 0x1C}},
    {'E', {0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x1F}},
    {'F', {0x1F, 0x10, 0x10, 0x1E, 0x10, 0x10, 0x10}},
    {'G', {0x0E, 0x11, 0x10, 0x17, 0x11, 0x11, 0x0F}},
    {'H', {0x11, 0x11, 0x11, 0x1F, 0x11, 0x11, 0x11}},
    {'I', {0x0E, 0x04, 0x04, 0x04, 0x04, 0x04, 0x0E}},
    {'J', {0x07, 0x02, 0x02, 0x02, 0x02, 0x12, 0x0C}},
    {'K', {0x11, 0x12, 0x14, 0x18, 0x14, 0x12, 0x11}},
    {'L', {0x10, 0x10, 0x10, 0x10, 0x10, 0x10, 0x1F}},
    {'M', {0x11, 0x1B, 0x15, 0x15, 0x11, 0x11, 0x11}},
    {'N', {0x11, 0x11, 0x19, 0x15, 0x13, 0x11, 0x11}},
    {'O', {0x0E, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E}},
    {'P', {0x1E, 0x11, 0x11, 0x1E, 0x10, 0x10, 0x10}},
    {'Q', {0x0E, 0x11, 0x11, 0x11, 0x15, 0x12, 0x0D}},
    {'R', {0x1E, 0x11, 0x11, 0x1E, 0x14, 0x12, 0x11}},
    {'S', {0x0F, 0x10, 0x10, 0x0E, 0x01, 0x01, 0x1E}},
    {'T', {0x1F, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04}},
    {'U', {0x11, 0x11, 0x11, 0x11, 0x11, 0x11, 0x0E}},
    {'V', {0x11, 0x11, 0x11, 0x11, 0x11, 0x0A, 0x04}},
    {'W', {0x11, 0x11, 0x11, 0x15, 0x15, 0x15, 0x0A}},
    {'X', {0x11, 0x11, 0x0A, 0x04, 0x0A, 0x11, 0x11}},
    {'Y', {0x11, 0x11, 0x0A, 0x04, 0x04, 0x04, 0x04}},
    {'Z', {0x1F, 0x01, 0x02, 0x04, 0x08, 0x10, 0x1F}},
    {'.', {0x00, 0x00, 0x00, 0x00, 0x00, 0x0C, 0x0C}},
    {',', {0x00, 0x00, 0x00, 0x00, 0x0C, 0x04, 0x08}},
    {'-', {0x00, 0x00, 0x00, 0x1F, 0x00, 0x00, 0x00}},
    {'+', {0x00, 0x04, 0x04, 0x1F, 0x04, 0x04, 0x00}},
    {'=', {0x00, 0x00, 0x1F, 0x00, 0x1F, 0x00, 0x00}},
    {':', {0x00, 0x0C, 0x0C, 0x00, 0x0C, 0x0C, 0x00}},
    {'%', {0x18, 0x19, 0x02, 0x04, 0x08, 0x13, 0x03}},
    {'(', {0x02, 0x04, 0x08, 0x08, 0x08, 0x04, 0x02}},
    {')', {0x08, 0x04, 0x02, 0x02, 0x02, 0x04, 0x08}},
    {'/', {0x00, 0x01, 0x02, 0x04, 0x08, 0x10, 0x00}},
    {'|', {0x04, 0x04, 0x04, 0x04, 0x04, 0x04, 0x04}},
    {'?', {0x0E, 0x11, 0x01, 0x02, 0x04, 0x00, 0x04}},
    {' ', {0, 0, 0, 0, 0, 0, 0}},
};

const Glyph& Find(char c) {
  c = static_cast<char>(std::toupper(static_cast<unsigned char>(c)));
  for (const Glyph& g : kFont) {
    if (g.c == c) return g;
  }
  for (const Glyph& g : kFont) {
    if (g.c == '?') return g;
  }
  return kFont[0];
}

}  // namespace

Canvas::Canvas(int width, int height, Rgb8 fill) {
  image_.width = std::max(1, width);
  image_.height = std::max(1, height);
  image_.channels = 3;
  image_.pixels.resize(size_t(image_.width) * image_.height * 3);
  for (size_t i = 0; i < image_.pixels.size(); i += 3)
    std::copy_n(fill.begin(), 3, &image_.pixels[i]);
}

void Canvas::Set(int x, int y, Rgb8 c) {
  if (x < 0 || y < 0 || x >= image_.width || y >= image_.height) return;
  std::copy_n(c.begin(), 3, &image_.pixels[3 * (size_t(y) * image_.width + x)]);
}

void Canvas::FillRect(int x, int y, int w, int h, Rgb8 c) {
  const int x0 = std::max(0, x), y0 = std::max(0, y);
  const int x1 = std::min(image_.width, x + w), y1 = std::min(image_.height, y + h);
  for (int yy = y0; yy < y1; ++yy)
    for (int xx = x0; xx < x1; ++xx) Set(xx, yy, c);
}

void Canvas::StrokeRect(int x, int y, int w, int h, Rgb8 c) {
  FillRect(x, y, w, 1, c);
  FillRect(x, y + h - 1, w, 1, c);
  FillRect(x, y, 1, h, c);
  FillRect(x + w - 1, y, 1, h, c);
}

void Canvas::Line(double x0, double y0, double x1, double y1, Rgb8 c, int thickness) {
  const double len = std::max(std::abs(x1 - x0), std::abs(y1 - y0));
  const int n = static_cast<int>(std::ceil(std::min(len, 1e5))) + 1;
  const int r0 = (thickness - 1) / 2, r1 = thickness / 2;
  for (int i = 0; i < n; ++i) {
    const double t = n > 1 ? double(i) / (n - 1) : 0;
    const int x = static_cast<int>(std::lround(x0 + t * (x1 - x0)));
    const int y = static_cast<int>(std::lround(y0 + t * (y1 - y0)));
    FillRect(x - r0, y - r0, r0 + r1 + 1, r0 + r1 + 1, c);
  }
}

void Canvas::Blit(const Image& src, int x, int y) {
  for (int yy = 0; yy < src.height; ++yy) {
    for (int xx = 0; xx < src.width; ++xx) {
      const uint8_t* p = &src.pixels[size_t(src.channels) * (size_t(yy) * src.width + xx)];
      Set(x + xx, y + yy, {p[0], p[1], p[2]});
    }
  }
}

int Canvas::Text(int x, int y, const std::string& text, Rgb8 c, int scale) {
  int cx = x;
  for (char ch : text) {
    const Glyph& g = Find(ch);
    for (int row = 0; row < 7; ++row) {
      for (int col = 0; col < 5; ++col) {
        if (g.rows[row] & (0x10 >> col))
          FillRect(cx + col * scale, y + row * scale, scale, scale, c);
      }
    }
    cx += 6 * scale;
  }
  return cx - x;
}

int Canvas::TextWidth(const std::string& text, int scale) {
  return text.empty() ? 0 : static_cast<int>(text.size()) * 6 * scale - scale;
}

Rgb8 HeatColor(double t) {
  struct Stop {
    double t;
    double r, g, b;
  };
  static constexpr Stop kStops[] = {{0.00, 0, 0, 4},
                                    {0.25, 87, 16, 110},
                                    {0.50, 188, 55, 84},
                                    {0.75, 249, 142, 9},
                                    {1.00, 252, 255, 164}};
  if (!(t > 0)) t = 0;
  if (t > 1) t = 1;
  int i = 0;
  while (i < 3 && t > kStops[i + 1].t) ++i;
  const Stop &a = kStops[i], &b = kStops[i + 1];
  const double f = (t - a.t) / (b.t - a.t);
  return {static_cast<uint8_t>(std::lround(a.r + f * (b.r - a.r))),
          static_cast<uint8_t>(std::lround(a.g + f * (b.g - a.g))),
          static_cast<uint8_t>(std::lround(a.b + f * (b.b - a.b)))};
}

std::string FormatNumber(double v) {
  if (!std::isfinite(v)) return "?";
  char buf[32];
  const double a = std::abs(v);
  if (a >= 1e6) {
    std::snprintf(buf, sizeof buf, "%.3gM", v / 1e6);
  } else if (a >= 1e4) {
    std::snprintf(buf, sizeof buf, "%.3gK", v / 1e3);
  } else {
    std::snprintf(buf, sizeof buf, "%.4g", v);
  }
  return buf;
}

}  // namespace decima
