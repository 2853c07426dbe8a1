#include "core/render/annotate.h"

#include <algorithm>
#include <cmath>

#include "absl/strings/str_cat.h"
#include "core/render/canvas.h"

namespace decima {
namespace {

constexpr Rgb8 kInk{235, 235, 235};
constexpr Rgb8 kShadow{0, 0, 0};
constexpr Rgb8 kFooterFill{24, 24, 28};

// 5x7 glyphs at 1x up to 767 px wide, 2x above: readable without covering the picture.
int ScaleFor(int width) { return std::clamp(width / 384, 1, 2); }

// Text with a 1-pixel dark outline so it reads on bright and dark tissue alike.
void OutlinedText(Canvas& c, int x, int y, const std::string& t, int s) {
  for (int dx = -1; dx <= 1; ++dx) {
    for (int dy = -1; dy <= 1; ++dy) {
      if (dx != 0 || dy != 0) c.Text(x + dx, y + dy, t, kShadow, s);
    }
  }
  c.Text(x, y, t, kInk, s);
}

// Words of `line` wrapped to at most `max_chars` characters per line.
std::vector<std::string> Wrap(const std::string& line, size_t max_chars) {
  std::vector<std::string> out;
  std::string cur;
  size_t start = 0;
  while (start <= line.size()) {
    size_t end = line.find(' ', start);
    if (end == std::string::npos) end = line.size();
    std::string word = line.substr(start, end - start);
    while (word.size() > max_chars) {  // a path longer than the picture: hard break
      if (!cur.empty()) out.push_back(std::move(cur)), cur.clear();
      out.push_back(word.substr(0, max_chars));
      word = word.substr(max_chars);
    }
    if (!cur.empty() && cur.size() + 1 + word.size() > max_chars) {
      out.push_back(std::move(cur));
      cur.clear();
    }
    if (!word.empty()) cur += (cur.empty() ? "" : " ") + word;
    start = end + 1;
  }
  if (!cur.empty()) out.push_back(cur);
  return out;
}

}  // namespace

std::string OrientationLetters(const Eigen::Vector3d& d) {
  const char pos[3] = {'L', 'P', 'S'}, neg[3] = {'R', 'A', 'I'};
  const double n = d.norm();
  if (!(n > 0)) return "";
  int order[3] = {0, 1, 2};
  std::sort(order, order + 3, [&](int a, int b) { return std::abs(d[a]) > std::abs(d[b]); });
  std::string out(1, d[order[0]] > 0 ? pos[order[0]] : neg[order[0]]);
  if (std::abs(d[order[1]]) >= n / 3) out += d[order[1]] > 0 ? pos[order[1]] : neg[order[1]];
  return out;
}

double ScaleBarMm(double pixels_per_mm, int width_px) {
  const double steps[] = {500, 200, 100, 50, 20, 10, 5, 2, 1};
  for (double mm : steps) {
    if (mm * pixels_per_mm <= width_px / 4.0) return mm;
  }
  return 1;
}

Image AddFooter(const Image& image, const std::vector<std::string>& footer) {
  const int s = ScaleFor(image.width);
  const int pad = 4 * s, line_h = 9 * s;
  const size_t max_chars = static_cast<size_t>(std::max(8, (image.width - 2 * pad) / (6 * s)));
  std::vector<std::string> lines;
  for (const auto& f : footer) {
    for (auto& w : Wrap(f, max_chars)) lines.push_back(std::move(w));
  }
  const int strip = lines.empty() ? 0 : 2 * pad + line_h * static_cast<int>(lines.size());
  Canvas c(image.width, image.height + strip, kFooterFill);
  Image rgb = image;
  if (rgb.channels == 4) {
    Image three{rgb.width, rgb.height, 3, {}};
    three.pixels.reserve(size_t(rgb.width) * rgb.height * 3);
    for (size_t i = 0; i < rgb.pixels.size(); i += 4) {
      three.pixels.insert(three.pixels.end(), rgb.pixels.begin() + i, rgb.pixels.begin() + i + 3);
    }
    rgb = std::move(three);
  }
  c.Blit(rgb, 0, 0);
  for (size_t i = 0; i < lines.size(); ++i) {
    c.Text(pad, image.height + pad + static_cast<int>(i) * line_h, lines[i], kInk, s);
  }
  return c.Take();
}

Image AnnotateRender(const Image& render, const Camera& camera,
                     const std::vector<std::string>& footer) {
  Canvas c(render.width, render.height, kShadow);
  c.Blit(render, 0, 0);
  const int s = ScaleFor(render.width);
  const int m = 4 * s;
  const std::string right = OrientationLetters(camera.right),
                    left = OrientationLetters(-camera.right);
  const std::string top = OrientationLetters(camera.up), bottom = OrientationLetters(-camera.up);
  const int w = render.width, h = render.height, th = Canvas::TextHeight(s);
  OutlinedText(c, m, (h - th) / 2, left, s);
  OutlinedText(c, w - m - Canvas::TextWidth(right, s), (h - th) / 2, right, s);
  OutlinedText(c, (w - Canvas::TextWidth(top, s)) / 2, m, top, s);
  OutlinedText(c, (w - Canvas::TextWidth(bottom, s)) / 2, h - m - th, bottom, s);
  if (!camera.perspective) {
    const double ppm = camera.Scale();
    const double mm = ScaleBarMm(ppm, w);
    const int len = static_cast<int>(std::lround(mm * ppm));
    const int y = h - m - th - 3 * s;
    c.FillRect(m - 1, y - 1, len + 2, 2 * s + 2, kShadow);
    c.FillRect(m, y, len, 2 * s, kInk);
    c.FillRect(m, y - 3 * s, s, 3 * s, kInk);
    c.FillRect(m + len - s, y - 3 * s, s, 3 * s, kInk);
    OutlinedText(c, m, y + 3 * s, absl::StrCat(mm, " MM"), s);
  }
  return AddFooter(c.Take(), footer);
}

}  // namespace decima
