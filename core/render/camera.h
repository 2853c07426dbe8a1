// Cameras for the tetrahedral volume renderer, in the mesh's LPS millimetre frame
// (x: towards the patient's left, y: posterior, z: superior).
//
// A camera maps pixel (i, j) (column i from the left, row j from the top, centre at integer
// coordinates) to a ray. `right`, `up` and `forward` are orthonormal with
// right = forward x up. Orthographic rays are parallel to `forward` and start on the plane
// through `eye` perpendicular to it; perspective rays start at `eye`.
#pragma once

#include <string>

#include <Eigen/Core>
#include <Eigen/Geometry>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace decima {

struct Camera {
  int width = 512;   // pixels
  int height = 512;  // pixels
  bool perspective = false;
  Eigen::Vector3d eye{0, 0, 0};
  Eigen::Vector3d forward{0, 1, 0};
  Eigen::Vector3d up{0, 0, 1};
  Eigen::Vector3d right{1, 0, 0};
  // Orthographic: width of the image plane in mm (height follows from the pixel aspect 1:1).
  double ortho_width_mm = 256;
  // Perspective: full vertical field of view in degrees, in (0, 180).
  double fov_y_deg = 30;

  // Focal length in pixels (perspective) or pixels per mm (orthographic).
  double Scale() const;
  // Ray of pixel centre (px, py) (integers at pixel centres; fractions allowed): origin on the
  // camera plane / at the eye, and direction with dot(direction, forward) == 1, so a ray
  // parameter t is the depth along `forward` and |direction| converts depth to path length.
  void Ray(double px, double py, Eigen::Vector3d* origin, Eigen::Vector3d* direction) const;
  // Screen position (pixel units, same convention) and depth along `forward` of point p.
  // Perspective: only meaningful for depth > 0.
  Eigen::Vector3d Project(const Eigen::Vector3d& p) const;
};

// Axis-aligned box in LPS mm.
struct Bounds {
  Eigen::Vector3d min{0, 0, 0};
  Eigen::Vector3d max{0, 0, 0};
  Eigen::Vector3d Center() const { return 0.5 * (min + max); }
  double Radius() const { return 0.5 * (max - min).norm(); }
};

// Direction the camera looks from. Azimuth and elevation in degrees, measured from the anterior
// view: azimuth 0 = anterior (eye at -y), 90 = from the patient's left (+x), 180 = posterior,
// -90 = right; elevation 90 = from above (superior), -90 = from below (inferior).
// The image's right vector is horizontal, (cos az, sin az, 0); up = right x forward.
struct ViewDirection {
  double azimuth_deg = 0;
  double elevation_deg = 0;
};

// Named views: "anterior" (0, 0): face on, z up, patient's left on the image's right;
// "posterior" (180, 0); "left" and "lateral" (90, 0); "right" (-90, 0); "superior" (0, 90):
// from above, posterior at the top; "inferior" (0, -90): from below, anterior at the top,
// patient's left on the right (the radiological axial convention); "oblique" (45, 30).
// Also "AZ,EL" in degrees (e.g. "30,15"). Errors: InvalidArgument listing the names.
absl::StatusOr<ViewDirection> ParseView(absl::string_view name);

struct ViewOptions {
  int width = 512;
  int height = 512;
  bool perspective = false;
  double fov_y_deg = 30;  // perspective only
  // Empty border around the projected bounds, as a fraction of the image (each side).
  double margin = 0.04;
};

// A camera looking at `bounds` from `view` so the whole box is in the image, centred, and
// the eye outside the box's bounding sphere (so every vertex lies in front of it).
// Use the bounds of the ORIGINAL mesh for both original and simplified renders so the
// pictures are comparable pixel by pixel. Errors: InvalidArgument for a size outside
// 1..8192, an empty or non-finite box, or a bad field of view.
absl::StatusOr<Camera> MakeViewCamera(const ViewDirection& view, const Bounds& bounds,
                                      const ViewOptions& options = {});

}  // namespace decima
