// The job-memory check both the submit (jobs_service) and the runner make
// (server/jobs/job_memory.h).
#include "server/jobs/job_memory.h"

#include <algorithm>

#include "gmock/gmock.h"
#include "gtest/gtest.h"

namespace decima::server {
namespace {

using ::testing::HasSubstr;

v1::Volume WithDims(std::initializer_list<int64_t> dims) {
  v1::Volume v;
  for (int64_t d : dims) v.add_dims(d);
  return v;
}

TEST(JobMemoryCheck, AVolumeUnderTheCapPassesAndOneOverItIsRefusedWithSizeEstimateLimitAndFlag) {
  const v1::Volume small = WithDims({64, 64, 64});
  const v1::Volume big = WithDims({511, 511, 897});
  const int64_t cap = int64_t{4} << 30;
  ASSERT_LT(EstimateJobMemoryBytes(small), cap);
  ASSERT_GT(EstimateJobMemoryBytes(big), cap);
  EXPECT_TRUE(CheckJobMemory(small, "volumes/small", cap).ok());
  const absl::Status refused = CheckJobMemory(big, "volumes/big", cap);
  EXPECT_EQ(refused.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(refused.message(), HasSubstr("volumes/big (511x511x897 voxels) needs about "));
  EXPECT_THAT(refused.message(), HasSubstr("more than the job limit of 4.0 GB"));
  EXPECT_THAT(refused.message(), HasSubstr("(decima-server --worker-memory-mb)"));
  // Exactly at the estimate fits.
  EXPECT_TRUE(CheckJobMemory(big, "volumes/big", EstimateJobMemoryBytes(big)).ok());
}

// The 511x511x225 CT of issue 30 (291 M tets): with the original's cells dropped while simplify
// runs and the original rendered from the grid, its peak stage is simplify (60 MiB + 58 B per
// tet, 15.8 GiB; 19.8 GiB before the cells were dropped) and render is below it (100 MiB + 44 B
// per tet, 12.0 GiB; 18.3 GiB with the materialized original), so it fits the 18.8 GiB default
// limit of a 24 GB machine with room to spare.
TEST(JobMemoryCheck, The511HeadCtIsEstimatedAtItsSimplifyStageUnderA24GBMachinesLimit) {
  const v1::Volume ct = WithDims({511, 511, 225});
  const int64_t tets = int64_t{5} * 510 * 510 * 224;
  const int64_t render = (int64_t{100} << 20) + 44 * tets;
  const int64_t simplify = (int64_t{60} << 20) + 58 * tets;
  EXPECT_EQ(EstimateJobMemoryBytes(ct), std::max(render, simplify));
  EXPECT_GT(simplify, render);
  EXPECT_TRUE(CheckJobMemory(ct, "volumes/ct", int64_t(16.0 * (int64_t{1} << 30))).ok());
  EXPECT_FALSE(CheckJobMemory(ct, "volumes/ct", int64_t(15.5 * (int64_t{1} << 30))).ok());
}

TEST(JobMemoryCheck, ADicomVolumeBeforeParsingIsNamedByItsBytes) {
  v1::Volume dicom;
  dicom.set_size_bytes(int64_t{2} * 512 * 512 * 1000);
  const absl::Status refused = CheckJobMemory(dicom, "volumes/ct", int64_t{1} << 30);
  EXPECT_EQ(refused.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_THAT(refused.message(), HasSubstr("volumes/ct (500 MB) needs about "));
}

TEST(JobMemoryCheck, TheCapIsTheFlagWhenSetElseTheDefault) {
  EXPECT_EQ(JobMemoryCapBytes(2048), int64_t{2048} << 20);
  EXPECT_EQ(JobMemoryCapBytes(0), DefaultJobMemoryCapBytes());
}

}  // namespace
}  // namespace decima::server
