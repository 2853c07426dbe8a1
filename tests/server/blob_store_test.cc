#include <fstream>

#include "gtest/gtest.h"
#include "server/blob_store.h"
#include "server/sha256.h"
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

TEST_F(BlobStoreTest, BadDigestIsRejected) {
  EXPECT_EQ(store_->OpenWriter("../../etc/passwd", 3, 0).status().code(),
            absl::StatusCode::kInvalidArgument);
  EXPECT_FALSE(store_->Has("../x"));
}

}  // namespace
}  // namespace decima::server
