// A small scan for pipeline tests whose regions get tissue names: the head phantom with
// Hounsfield-like means (air outside, a bone shell, soft tissue inside).
#pragma once

#include <filesystem>

#include <gtest/gtest.h>

#include "core/io/volume_io.h"
#include "core/volume/phantom.h"

namespace decima::testing {

// Writes the 24x24x20 phantom (2 mm voxels) as dir/hu-phantom.nii.gz and returns its path.
inline std::filesystem::path HuPhantomFile(const std::filesystem::path& dir) {
  HeadPhantomOptions o;
  o.dims = {24, 24, 20};
  o.spacing = {2, 2, 2};
  o.noise_sigma = 20;
  o.region_means = {-1000, 900, 40};
  auto p = MakeHeadPhantom(o);
  EXPECT_TRUE(p.ok()) << p.status();
  const std::filesystem::path path = dir / "hu-phantom.nii.gz";
  EXPECT_TRUE(io::WriteNifti(p->image, path).ok());
  return path;
}

}  // namespace decima::testing
