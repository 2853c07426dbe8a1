// Helpers for the render tests: small meshes with known fields and an independent reference
// integrator of the emission-absorption model over the voxel field.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <functional>
#include <limits>
#include <vector>

#include <gtest/gtest.h>

#include "core/mesh/tetrahedralize.h"
#include "core/render/camera.h"
#include "core/render/transfer_function.h"
#include "core/volume/volume.h"

namespace decima::testing {

// A volume whose voxel values are a linear ramp a + b.i + c.j + d.k of the voxel index (so the
// 5-tet piecewise-linear interpolation equals the trilinear one exactly), with anisotropic
// spacing and a non-zero origin so mm and index coordinates differ.
inline Volume RampVolume(std::array<int64_t, 3> dims, std::array<double, 4> coef,
                         Eigen::Vector3d spacing = {1.0, 1.5, 1.25},
                         Eigen::Vector3d origin = {-3.0, 2.0, 5.0}) {
  std::vector<float> v(dims[0] * dims[1] * dims[2]);
  for (int64_t k = 0; k < dims[2]; ++k)
    for (int64_t j = 0; j < dims[1]; ++j)
      for (int64_t i = 0; i < dims[0]; ++i)
        v[i + dims[0] * (j + dims[1] * k)] =
            static_cast<float>(coef[0] + coef[1] * i + coef[2] * j + coef[3] * k);
  auto vol = MakeFloatVolume(dims, std::move(v));
  EXPECT_TRUE(vol.ok()) << vol.status();
  vol->spacing = spacing;
  vol->origin = origin;
  return *std::move(vol);
}

inline TetMesh MeshOf(const Volume& v) {
  auto m = Tetrahedralize(v);
  EXPECT_TRUE(m.ok()) << m.status();
  return *std::move(m);
}

// Trilinear interpolation of the voxel values at LPS point p (identity direction), or NaN
// outside the voxel-centre box. Written from the Volume, not from the mesh.
inline double Trilinear(const Volume& v, const Eigen::Vector3d& p) {
  const Eigen::Vector3d g = (p - v.origin).cwiseQuotient(v.spacing);
  int64_t i0[3];
  double f[3];
  for (int a = 0; a < 3; ++a) {
    if (g[a] < -1e-9 || g[a] > v.dims[a] - 1 + 1e-9)
      return std::numeric_limits<double>::quiet_NaN();
    i0[a] = std::clamp<int64_t>(static_cast<int64_t>(std::floor(g[a])), 0, v.dims[a] - 2);
    f[a] = g[a] - i0[a];
  }
  double s = 0;
  for (int c = 0; c < 8; ++c) {
    const int dx = c & 1, dy = (c >> 1) & 1, dz = (c >> 2) & 1;
    const double w = (dx ? f[0] : 1 - f[0]) * (dy ? f[1] : 1 - f[1]) * (dz ? f[2] : 1 - f[2]);
    s += w * v.ValueAt(v.Index(i0[0] + dx, i0[1] + dy, i0[2] + dz));
  }
  return s;
}

// Whether the ray of pixel (px, py) passes through the box [lo, hi] (slab method).
inline bool RayHitsBox(const Camera& cam, double px, double py, const Eigen::Vector3d& lo,
                       const Eigen::Vector3d& hi) {
  Eigen::Vector3d o, d;
  cam.Ray(px, py, &o, &d);
  double t0 = -std::numeric_limits<double>::infinity(),
         t1 = std::numeric_limits<double>::infinity();
  for (int a = 0; a < 3; ++a) {
    if (d[a] == 0) {
      if (o[a] < lo[a] || o[a] > hi[a]) return false;
      continue;
    }
    double ta = (lo[a] - o[a]) / d[a], tb = (hi[a] - o[a]) / d[a];
    if (ta > tb) std::swap(ta, tb);
    t0 = std::max(t0, ta);
    t1 = std::min(t1, tb);
  }
  return t1 > t0;
}

// True if the ray of pixel (x, y) runs within `r` pixels of the silhouette of one of the boxes
// (some corner of the r-square around the pixel centre hits it, another does not): such rays
// are decided by tie-breaking, not by the integral, and the tests skip them.
inline bool NearSilhouette(const Camera& cam, int x, int y,
                           const std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>>& boxes,
                           double r = 0.02) {
  for (const auto& [lo, hi] : boxes) {
    const bool h = RayHitsBox(cam, x, y, lo, hi);
    for (double dx : {-r, r})
      for (double dy : {-r, r})
        if (RayHitsBox(cam, x + dx, y + dy, lo, hi) != h) return true;
  }
  return false;
}

struct ReferencePixel {
  std::array<double, 3> rgb{0, 0, 0};
  double alpha = 0;
  bool hit = false;
};

// Reference emission-absorption integral along the ray of pixel (px, py): the ray is clipped to
// the box [lo, hi] by the slab method, then integrated with `steps` midpoint samples of the
// field `field(p)` (NaN = outside the domain, contributes nothing), using
// TransferFunction::Evaluate.
inline ReferencePixel ReferenceRay(const Camera& cam, double px, double py,
                                   const Eigen::Vector3d& lo, const Eigen::Vector3d& hi,
                                   const std::function<double(const Eigen::Vector3d&)>& field,
                                   const TransferFunction& tf, int steps = 2000) {
  Eigen::Vector3d o, d;
  cam.Ray(px, py, &o, &d);
  double t0 = -std::numeric_limits<double>::infinity(),
         t1 = std::numeric_limits<double>::infinity();
  for (int a = 0; a < 3; ++a) {
    if (d[a] == 0) {
      if (o[a] < lo[a] || o[a] > hi[a]) return {};
      continue;
    }
    double ta = (lo[a] - o[a]) / d[a], tb = (hi[a] - o[a]) / d[a];
    if (ta > tb) std::swap(ta, tb);
    t0 = std::max(t0, ta);
    t1 = std::min(t1, tb);
  }
  ReferencePixel out;
  if (!(t1 > t0)) return out;
  out.hit = true;
  const double len = (t1 - t0) * d.norm(), dl = len / steps;
  double T = 1;
  for (int i = 0; i < steps; ++i) {
    const double t = t0 + (t1 - t0) * (i + 0.5) / steps;
    const double s = field(o + t * d);
    if (std::isnan(s)) continue;
    float rgb[3], op;
    tf.Evaluate(s, rgb, &op);
    const double a = 1 - std::exp(-double(op) * dl);
    for (int c = 0; c < 3; ++c) out.rgb[c] += T * a * rgb[c];
    T *= 1 - a;
  }
  out.alpha = 1 - T;
  return out;
}

}  // namespace decima::testing
