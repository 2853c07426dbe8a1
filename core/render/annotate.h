// Reading aids drawn on rendered pictures for radiologists: patient-orientation letters at the
// image edges, a millimetre scale bar, and a footer with the job's parameters. Drawn on copies;
// the measurements (diff1, diff2) are always taken on the plain renders.
#pragma once

#include <string>
#include <vector>

#include <Eigen/Core>

#include "core/io/png.h"
#include "core/render/camera.h"

namespace decima {

// Patient-orientation letters of an LPS direction: "L"/"R" (x), "P"/"A" (y), "S"/"I" (z), the
// dominant axis first; a second letter when that axis also carries at least a third of the
// direction (oblique views: "LA"). Empty for a zero vector.
std::string OrientationLetters(const Eigen::Vector3d& lps_direction);

// Length in mm of a scale bar for an orthographic image of `pixels_per_mm`: the largest of
// 1, 2, 5, 10, 20, 50, 100, 200, 500 mm that fits in a quarter of `width_px`.
double ScaleBarMm(double pixels_per_mm, int width_px);

// `render` (RGB) with orientation letters at the four edge midpoints (from `camera.right` and
// `camera.up`), a scale bar in the lower left (orthographic cameras only), and `footer` lines
// in a strip below the picture (wrapped to its width; nothing is clipped).
Image AnnotateRender(const Image& render, const Camera& camera,
                     const std::vector<std::string>& footer);

// Appends the footer strip (wrapped lines) below any image.
Image AddFooter(const Image& image, const std::vector<std::string>& footer);

}  // namespace decima
