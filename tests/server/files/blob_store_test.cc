#include <sys/stat.h>

#include <fstream>
#include <thread>

#include "gtest/gtest.h"
#include "server/files/blob_store.h"
#include "server/files/disk_space.h"
#include "server/jobs/job_memory.h"
#include "server/util/sha256.h"
#include "tests/testing/test_data.h"

namespace decima::server {
namespace {

std::string Sha(const std::string& data) {
  Sha256 h;
  h.Update(data.data(), data.size());
  return h.HexDigest();
}

TEST(Sha256Test, KnownVector) {
  EXPECT_EQ(Sha("abc"), "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
  EXPECT_TRUE(IsSha256Hex(Sha("")));
  EXPECT_FALSE(IsSha256Hex("ABC"));
}

class BlobStoreTest : public ::testing::Test {
 protected:
  void SetUp() override {
    auto s = LocalBlobStore::Open(testing::MakeScratchDir("blobs"), /*fsync=*/false);
    ASSERT_TRUE(s.ok());
    store_ = std::move(*s);
  }
  std::unique_ptr<LocalBlobStore> store_;
};

TEST_F(BlobStoreTest, InterruptedWriteResumesFromTheHeldPrefix) {
  std::string data(10000, 'x');
  for (size_t i = 0; i < data.size(); ++i) data[i] = static_cast<char>(i * 31);
  std::string sha = Sha(data);
  {
    auto w = store_->OpenWriter(sha, 10000, 0);
    ASSERT_TRUE(w.ok());
    ASSERT_TRUE((*w)->Append(data.data(), 4000).ok());
  }  // dropped without commit: the prefix stays
  BlobStatus st = store_->Status(sha, 10000);
  EXPECT_FALSE(st.complete);
  EXPECT_EQ(st.committed_size, 4000);
  EXPECT_EQ(store_->OpenWriter(sha, 10000, 0).status().code(),
            absl::StatusCode::kFailedPrecondition);
  auto w = store_->OpenWriter(sha, 10000, 4000);
  ASSERT_TRUE(w.ok()) << w.status();
  ASSERT_TRUE((*w)->Append(data.data() + 4000, 6000).ok());
  ASSERT_TRUE((*w)->Commit().ok());
  EXPECT_TRUE(store_->Has(sha));
  EXPECT_TRUE(store_->Status(sha, 10000).complete);
  EXPECT_EQ(*Sha256OfFile(*store_->LocalPath(sha)), sha);
}

TEST_F(BlobStoreTest, DigestMismatchStoresNothing) {
  std::string sha = Sha("expected");
  auto w = store_->OpenWriter(sha, 8, 0);
  ASSERT_TRUE(w.ok());
  ASSERT_TRUE((*w)->Append("somethin", 8).ok());
  absl::Status s = (*w)->Commit();
  EXPECT_EQ(s.code(), absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(store_->Has(sha));
  EXPECT_EQ(store_->Status(sha, 8).committed_size, 0);
}

TEST_F(BlobStoreTest, MoreDataThanDeclaredStoresNothing) {
  std::string sha = Sha("abc");
  auto w = store_->OpenWriter(sha, 3, 0);
  ASSERT_TRUE(w.ok());
  EXPECT_EQ((*w)->Append("abcd", 4).code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(store_->Status(sha, 3).committed_size, 0);
}

TEST_F(BlobStoreTest, SecondConcurrentWriterIsAborted) {
  std::string sha = Sha("abc");
  auto w1 = store_->OpenWriter(sha, 3, 0);
  ASSERT_TRUE(w1.ok());
  EXPECT_EQ(store_->OpenWriter(sha, 3, 0).status().code(), absl::StatusCode::kAborted);
  w1->reset();
  EXPECT_TRUE(store_->OpenWriter(sha, 3, 0).ok());
}

// Replicas share one blob folder: a writer in another process (here another store on the same
// folder, a separate open file description) holds the upload's flock; the writer it refused
// can resume once the first is gone, at the prefix the first left.
TEST(SharedBlobFolderTest, AWriterOfAnotherStoreOnTheFolderIsAbortedThenResumes) {
  const auto root = testing::MakeScratchDir("shared_blobs");
  auto a = LocalBlobStore::Open(root, false);
  auto b = LocalBlobStore::Open(root, false);
  ASSERT_TRUE(a.ok() && b.ok());
  const std::string data(1000, 'q');
  const std::string sha = Sha(data);
  auto wa = (*a)->OpenWriter(sha, 1000, 0);
  ASSERT_TRUE(wa.ok()) << wa.status();
  ASSERT_TRUE((*wa)->Append(data.data(), 400).ok());
  auto wb = (*b)->OpenWriter(sha, 1000, 400);
  EXPECT_EQ(wb.status().code(), absl::StatusCode::kAborted) << wb.status();
  EXPECT_NE(std::string(wb.status().message()).find("another upload"), std::string::npos);
  wa->reset();  // A's stream ends: its prefix stays
  EXPECT_EQ((*b)->Status(sha, 1000).committed_size, 400);
  wb = (*b)->OpenWriter(sha, 1000, 400);
  ASSERT_TRUE(wb.ok()) << wb.status();
  ASSERT_TRUE((*wb)->Append(data.data() + 400, 600).ok());
  ASSERT_TRUE((*wb)->Commit().ok());
  EXPECT_TRUE((*a)->Has(sha));
}

TEST_F(BlobStoreTest, BadDigestIsRejected) {
  EXPECT_EQ(store_->OpenWriter("../../etc/passwd", 3, 0).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(store_->Has("../x"));
}

// Sets a file's modification time `age` into the past (what a sweep reads as claim / idle time).
void Age(const std::filesystem::path& p, std::chrono::seconds age) {
  std::filesystem::last_write_time(p, std::filesystem::file_time_type::clock::now() - age);
}

std::string Commit(LocalBlobStore& store, const std::string& data) {
  const std::string sha = Sha(data);
  auto w = store.OpenWriter(sha, static_cast<int64_t>(data.size()), 0);
  EXPECT_TRUE(w.ok());
  EXPECT_TRUE((*w)->Append(data.data(), data.size()).ok());
  EXPECT_TRUE((*w)->Commit().ok());
  return sha;
}

TEST_F(BlobStoreTest, SweepKeepsClaimedAndReferencedBlobsAndRemovesTheRest) {
  const std::string kept_by_claim = Commit(*store_, "fresh upload");
  const std::string referenced = Commit(*store_, "used by a volume");
  const std::string orphan = Commit(*store_, "nobody's");
  const std::string reclaimed = Commit(*store_, "found again by a dedup upload");
  for (const auto& sha : {referenced, orphan, reclaimed}) {
    Age(store_->BlobPath(sha), std::chrono::hours(2));
  }
  store_->Claim(reclaimed);  // its grace starts again
  BlobSweepPolicy policy;    // grace 1 h
  auto in_use = [&](const std::string& sha) { return sha == referenced; };
  const BlobSweepStats st = store_->Sweep(policy, in_use);
  EXPECT_EQ(st.blobs_removed, 1);
  EXPECT_EQ(st.bytes_freed, 8);
  EXPECT_FALSE(store_->Has(orphan));
  EXPECT_TRUE(store_->Has(kept_by_claim));
  EXPECT_TRUE(store_->Has(referenced));
  EXPECT_TRUE(store_->Has(reclaimed));
}

TEST_F(BlobStoreTest, SweepRemovesIdlePartialsButNotOneBeingWritten) {
  const std::string idle(1000, 'i'), active(1000, 'a');
  {
    auto w = store_->OpenWriter(Sha(idle), 1000, 0);
    ASSERT_TRUE(w.ok());
    ASSERT_TRUE((*w)->Append(idle.data(), 10).ok());
  }
  auto writer = store_->OpenWriter(Sha(active), 1000, 0);
  ASSERT_TRUE(writer.ok());
  ASSERT_TRUE((*writer)->Append(active.data(), 10).ok());
  Age(store_->PartialPath(Sha(idle), 1000), std::chrono::hours(25));
  Age(store_->PartialPath(Sha(active), 1000), std::chrono::hours(25));
  const BlobSweepStats st =
      store_->Sweep(BlobSweepPolicy{}, [](const std::string&) { return false; });
  EXPECT_EQ(st.partials_removed, 1);
  EXPECT_EQ(store_->Status(Sha(idle), 1000).committed_size, 0);
  EXPECT_EQ(store_->Status(Sha(active), 1000).committed_size, 10);
  // The writer goes on and commits.
  ASSERT_TRUE((*writer)->Append(active.data() + 10, 990).ok());
  EXPECT_TRUE((*writer)->Commit().ok());
}

TEST_F(BlobStoreTest, SweepOfNamedBlobsLooksAtThoseOnly) {
  const std::string a = Commit(*store_, "a-bytes"), b = Commit(*store_, "b-bytes");
  Age(store_->BlobPath(a), std::chrono::hours(2));
  Age(store_->BlobPath(b), std::chrono::hours(2));
  const std::vector<std::string> only = {a};
  store_->Sweep(
      BlobSweepPolicy{}, [](const std::string&) { return false; }, &only);
  EXPECT_FALSE(store_->Has(a));
  EXPECT_TRUE(store_->Has(b));
}

TEST(DiskSpaceTest, AdmitNamesNeededAndFreeBytes) {
  DiskSpace disk(testing::MakeScratchDir("disk"), 0);
  const int64_t free = disk.Free();
  ASSERT_GT(free, 0);
  EXPECT_TRUE(disk.Admit(1, "upload").ok());
  const absl::Status st = disk.Admit(free + (int64_t{1} << 40), "upload of blob x");
  EXPECT_EQ(st.code(), absl::StatusCode::kResourceExhausted);
  EXPECT_NE(std::string(st.message()).find("upload of blob x needs"), std::string::npos) << st;
  EXPECT_NE(std::string(st.message()).find("free"), std::string::npos) << st;
  EXPECT_EQ(HumanBytes(512), "512 bytes");
  EXPECT_EQ(HumanBytes(int64_t{3} << 30), "3.0 GB");
}

TEST(DiskSpaceTest, ReserveIsAllocatedAndReleasedOnlyWhenTheDiskIsNearlyFull) {
  const auto dir = testing::MakeScratchDir("reserve");
  DiskSpace disk(dir, int64_t{1} << 20);
  ASSERT_TRUE(disk.Refill());
  EXPECT_EQ(std::filesystem::file_size(disk.reserve_file()), 1u << 20);
  disk.BeforeDelete();  // plenty of room here: the reserve stays
  EXPECT_TRUE(std::filesystem::exists(disk.reserve_file()));
}

TEST(JobMemoryTest, EstimateGrowsWithVoxelsAndFallsBackToFileSize) {
  v1::Volume small, big, dicom;
  for (int64_t d : {64, 64, 64}) small.add_dims(d);
  for (int64_t d : {2048, 1024, 1024}) big.add_dims(d);
  dicom.set_size_bytes(int64_t{2} * 512 * 512 * 100);  // 100 int16 slices
  EXPECT_LT(EstimateJobMemoryBytes(small), int64_t{512} << 20);
  EXPECT_GT(EstimateJobMemoryBytes(big), int64_t{1} << 39);
  EXPECT_GT(EstimateJobMemoryBytes(dicom), int64_t{512} * 512 * 100 * 256);
  // The limit leaves room for twice the estimate but never exceeds the cap.
  EXPECT_EQ(JobAddressSpaceLimitBytes(int64_t{1} << 30, int64_t{64} << 30), int64_t{3} << 30);
  EXPECT_EQ(JobAddressSpaceLimitBytes(int64_t{40} << 30, int64_t{64} << 30), int64_t{64} << 30);
  EXPECT_GT(DefaultJobMemoryCapBytes(), 0);
}

// The estimate against the job peaks `decima-bench --job-out` measured (core/pipeline/README.md,
// "Memory"; 50 %, field policy): within 25 %, the band issue 30 asks for. A change of the
// pipeline's memory that moves a peak out of the band must come with new figures and constants.
TEST(JobMemoryTest, EstimateIsWithinAQuarterOfTheMeasuredPeaks) {
  struct Measured {
    int64_t dims[3];
    double peak_mib;
  };
  // With the original rendered from the grid (issue 30) every job's peak is its simplify stage:
  // the CT heads measured so; ch2 its simplify stage measured with the cells dropped (its render
  // is below, as on the heads); ch2better its simplify stage at 80 % with the grid render (a job
  // through decima-bench --job-out; render 5387); the 511 CT its simplify stage through the
  // server at 80 % (its render, 16507, was measured from the mesh).
  for (const Measured& m : {Measured{{128, 128, 53}, 287},        // CT head, small
                            Measured{{256, 256, 113}, 2028},      // CT head
                            Measured{{181, 217, 181}, 2034},      // ch2
                            Measured{{301, 370, 316}, 9489},      // ch2better
                            Measured{{511, 511, 225}, 15318}}) {  // 511 CT
    v1::Volume v;
    for (int64_t d : m.dims) v.add_dims(d);
    const double estimate_mib = EstimateJobMemoryBytes(v) / 1048576.0;
    EXPECT_GT(estimate_mib, 0.75 * m.peak_mib) << m.dims[0] << "x" << m.dims[1] << "x" << m.dims[2];
    EXPECT_LT(estimate_mib, 1.25 * m.peak_mib) << m.dims[0] << "x" << m.dims[1] << "x" << m.dims[2];
  }
}

}  // namespace
}  // namespace decima::server
