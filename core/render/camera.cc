#include "core/render/camera.h"

#include <algorithm>
#include <cmath>
#include <vector>

#include "absl/strings/ascii.h"
#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"

namespace decima {
namespace {

constexpr double kPi = 3.14159265358979323846;
double Radians(double deg) { return deg * kPi / 180.0; }

}  // namespace

double Camera::Scale() const {
  if (perspective) return 0.5 * height / std::tan(Radians(0.5 * fov_y_deg));
  return width / ortho_width_mm;
}

void Camera::Ray(double px, double py, Eigen::Vector3d* origin, Eigen::Vector3d* direction) const {
  const double s = Scale();
  const double x = (px - 0.5 * (width - 1)) / s, y = (0.5 * (height - 1) - py) / s;
  if (perspective) {
    *origin = eye;
    *direction = forward + x * right + y * up;
  } else {
    *origin = eye + x * right + y * up;
    *direction = forward;
  }
}

Eigen::Vector3d Camera::Project(const Eigen::Vector3d& p) const {
  const Eigen::Vector3d q = p - eye;
  const double depth = q.dot(forward);
  double x = q.dot(right), y = q.dot(up);
  const double s = Scale();
  if (perspective) {
    x /= depth;
    y /= depth;
  }
  return {0.5 * (width - 1) + s * x, 0.5 * (height - 1) - s * y, depth};
}

absl::StatusOr<ViewDirection> ParseView(absl::string_view name) {
  const std::string n = absl::AsciiStrToLower(absl::StripAsciiWhitespace(name));
  struct Named {
    const char* name;
    double az, el;
  };
  static constexpr Named kViews[] = {
      {"anterior", 0, 0}, {"posterior", 180, 0}, {"left", 90, 0},      {"lateral", 90, 0},
      {"right", -90, 0},  {"superior", 0, 90},   {"inferior", 0, -90}, {"oblique", 45, 30}};
  for (const Named& v : kViews) {
    if (n == v.name) return ViewDirection{v.az, v.el};
  }
  // "AZ,EL" or "AZ:EL" (the colon survives command lines that split lists on commas).
  std::vector<std::string> parts = absl::StrSplit(n, absl::ByAnyChar(",:"));
  ViewDirection d;
  if (parts.size() == 2 && absl::SimpleAtod(absl::StripAsciiWhitespace(parts[0]), &d.azimuth_deg) &&
      absl::SimpleAtod(absl::StripAsciiWhitespace(parts[1]), &d.elevation_deg) &&
      std::isfinite(d.azimuth_deg) && std::abs(d.elevation_deg) <= 90) {
    return d;
  }
  return absl::InvalidArgumentError(absl::StrCat(
      "view '", name,
      "': expected anterior, posterior, left, lateral, right, superior, inferior, oblique or "
      "'AZIMUTH:ELEVATION' (or 'AZIMUTH,ELEVATION') in degrees with |elevation| <= 90"));
}

absl::StatusOr<Camera> MakeViewCamera(const ViewDirection& view, const Bounds& bounds,
                                      const ViewOptions& options) {
  if (options.width < 1 || options.width > 8192 || options.height < 1 || options.height > 8192) {
    return absl::InvalidArgumentError(absl::StrCat("camera: image size ", options.width, "x",
                                                   options.height, " is not in 1..8192"));
  }
  if (!bounds.min.allFinite() || !bounds.max.allFinite() ||
      !(bounds.max.array() >= bounds.min.array()).all() || bounds.Radius() <= 0) {
    return absl::InvalidArgumentError("camera: the mesh bounds are empty or not finite");
  }
  if (options.perspective && !(options.fov_y_deg > 0 && options.fov_y_deg < 180)) {
    return absl::InvalidArgumentError(
        absl::StrCat("camera: fov_y_deg ", options.fov_y_deg, " is not in (0, 180)"));
  }
  if (!(options.margin >= 0 && options.margin < 0.45)) {
    return absl::InvalidArgumentError(
        absl::StrCat("camera: margin ", options.margin, " is not in [0, 0.45)"));
  }
  if (!std::isfinite(view.azimuth_deg) || !(std::abs(view.elevation_deg) <= 90)) {
    return absl::InvalidArgumentError("camera: azimuth must be finite, |elevation| <= 90");
  }
  const double az = Radians(view.azimuth_deg), el = Radians(view.elevation_deg);
  const Eigen::Vector3d to_eye(std::sin(az) * std::cos(el), -std::cos(az) * std::cos(el),
                               std::sin(el));
  Camera cam;
  cam.width = options.width;
  cam.height = options.height;
  cam.perspective = options.perspective;
  cam.fov_y_deg = options.fov_y_deg;
  cam.forward = -to_eye.normalized();
  cam.right = Eigen::Vector3d(std::cos(az), std::sin(az), 0);
  cam.up = cam.right.cross(cam.forward).normalized();
  cam.right = cam.forward.cross(cam.up).normalized();

  const Eigen::Vector3d c = bounds.Center();
  const double r = bounds.Radius();
  const double fill = 1.0 - 2.0 * options.margin;
  const double aspect = double(options.width) / options.height;
  if (options.perspective) {
    // The bounding sphere fits in the narrower of the two view cones.
    const double half_y = Radians(0.5 * options.fov_y_deg);
    const double half_x = std::atan(std::tan(half_y) * aspect);
    const double d = r / std::sin(std::min(half_x, half_y) * fill);
    cam.eye = c - d * cam.forward;
  } else {
    double ex = 0, ey = 0;
    for (int k = 0; k < 8; ++k) {
      const Eigen::Vector3d corner((k & 1) ? bounds.max.x() : bounds.min.x(),
                                   (k & 2) ? bounds.max.y() : bounds.min.y(),
                                   (k & 4) ? bounds.max.z() : bounds.min.z());
      ex = std::max(ex, std::abs((corner - c).dot(cam.right)));
      ey = std::max(ey, std::abs((corner - c).dot(cam.up)));
    }
    cam.ortho_width_mm = std::max({2 * ex, 2 * ey * aspect, 1e-6}) / fill;
    cam.eye = c - (2 * r + 1) * cam.forward;
  }
  return cam;
}

}  // namespace decima
