// Transfer functions: scalar value -> emitted colour and extinction (opacity per mm).
//
// A transfer function is a list of control points sorted by strictly increasing value; colour
// and opacity are interpolated linearly between neighbouring points and held constant beyond
// the first and last point. Opacity is an extinction coefficient in 1/mm (the fraction of light
// absorbed per mm is 1 - exp(-opacity)), so images do not depend on the sampling step.
//
// JSON file format (all keys required unless marked optional):
//   {
//     "name": "my-tf",                       (optional, string)
//     "domain": "absolute" | "relative",     (optional, default "absolute"; "relative" values
//                                             are fractions 0..1 of the data range)
//     "points": [ {"value": -1000, "rgb": [0, 0, 0], "opacity": 0},
//                 {"value":   300, "rgb": [1, 0.95, 0.9], "opacity": 0.4}, ... ]
//   }
// rgb components in 0..1, opacity >= 0 (per mm), values strictly increasing, 1..256 points.
#pragma once

#include <array>
#include <filesystem>
#include <string>
#include <vector>

#include "absl/status/statusor.h"
#include "absl/strings/string_view.h"

namespace decima {

struct TransferPoint {
  double value = 0;                   // scalar value (the mesh's units)
  std::array<float, 3> rgb{0, 0, 0};  // emitted colour, 0..1
  float opacity = 0;                  // extinction coefficient, 1/mm, >= 0
};

struct TransferFunction {
  std::string name;
  std::vector<TransferPoint> points;  // strictly increasing value, at least one

  // Colour and extinction at scalar s (linear interpolation, clamped at the ends).
  void Evaluate(double s, float rgb[3], float* opacity) const;
  // Returns OK if the invariants above hold, else InvalidArgument naming the first bad point.
  absl::Status Validate() const;
};

// Range of the data the transfer function will be applied to (the ORIGINAL mesh's scalars, so
// original and simplified renders share one transfer function).
struct ScalarRange {
  double min = 0;
  double max = 1;
};

// Presets:
//  "ct": skin (faint orange), soft tissue (faint red) and bone (ivory, extinction rising with
//        density); defined in Hounsfield units. Data whose minimum is above -500 is taken to be
//        stored as HU + 1024 (no air at -1000 HU; the shared CT heads are stored so), and the
//        preset is shifted by +1024 for it.
//  "ct-bone": only bone, opaque; same HU rule.
//  "mri-t1": T1-weighted MRI, relative to the data range: background transparent, CSF dark,
//        grey and white matter in increasing brightness, fat brightest.
// Errors: InvalidArgument naming the known presets; InvalidArgument for an empty or
// non-finite range (relative presets only).
absl::StatusOr<TransferFunction> TransferFunctionPreset(absl::string_view name,
                                                        const ScalarRange& data_range);

// Parses the JSON format above; `what` (a file name) starts every error message. Relative
// domains are mapped onto `data_range`. Errors: InvalidArgument naming the key and what was
// expected (not JSON, missing "points", wrong types, rgb not 3 numbers in 0..1, negative or
// non-finite opacity, values not strictly increasing, no points or more than 256).
absl::StatusOr<TransferFunction> ParseTransferFunction(
    absl::string_view json, const ScalarRange& data_range,
    absl::string_view what = "transfer function");

// Reads and parses a file (at most 1 MiB). Errors: NotFound, or the parse errors above
// prefixed with the path.
absl::StatusOr<TransferFunction> LoadTransferFunction(const std::filesystem::path& path,
                                                      const ScalarRange& data_range);

// Serializes to the JSON format (absolute domain); ParseTransferFunction reads it back.
std::string TransferFunctionToJson(const TransferFunction& tf);

}  // namespace decima
