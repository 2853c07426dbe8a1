// The .levels file: what is written reads back the same, and every damaged or foreign file is
// refused with what is wrong, never a crash or a huge allocation.
#include <cstring>
#include <filesystem>
#include <string>

#include <gtest/gtest.h>
#include <unistd.h>

#include "core/simplify/levels.h"
#include "core/simplify/levels_io.h"
#include "tests/core/simplify/simplify_test_util.h"

namespace decima {
namespace {

using testing::MakePhantomMesh;

SimplifyLevels Record(const TetMesh& mesh, double floor) {
  SimplifyOptions o;
  o.policy = SimplifyPolicy::kField;
  o.target_reduction = 0.2;
  o.record_levels_to = floor;
  auto r = Simplify(mesh, o);
  EXPECT_TRUE(r.ok()) << r.status();
  return *r->levels;
}

template <typename T>
void Poke(std::string* bytes, size_t at, T v) {
  std::memcpy(bytes->data() + at, &v, sizeof(T));
}

void ExpectRefused(const std::string& bytes, const std::string& words) {
  auto r = ParseLevels(bytes, "x.levels");
  ASSERT_FALSE(r.ok()) << words;
  EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_NE(std::string(r.status().message()).find(words), std::string::npos) << r.status();
  EXPECT_NE(std::string(r.status().message()).find("x.levels"), std::string::npos);
}

TEST(LevelsFile, RoundTripsAndItsLevelsAreTheRecordsLevels) {
  auto pm = MakePhantomMesh(20, 40);
  const SimplifyLevels levels = Record(pm.mesh, 0.6);
  const std::filesystem::path path =
      std::filesystem::temp_directory_path() / ("levels-" + std::to_string(::getpid()));
  ASSERT_TRUE(WriteLevels(levels, path).ok());
  auto back = ReadLevels(path);
  std::filesystem::remove(path);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->removed_vertex, levels.removed_vertex);
  EXPECT_EQ(back->survivor, levels.survivor);
  EXPECT_EQ(back->cells_deleted, levels.cells_deleted);
  EXPECT_EQ(back->base_vertices, levels.base_vertices);
  EXPECT_EQ(back->base_cells, levels.base_cells);
  EXPECT_EQ(back->refit_iterations, levels.refit_iterations);
  EXPECT_EQ(back->exhausted, levels.exhausted);
  EXPECT_EQ(back->base_digest, levels.base_digest);
  auto a = ExtractLevel(pm.mesh, levels, 0.5);
  auto b = ExtractLevel(pm.mesh, *back, 0.5);
  ASSERT_TRUE(a.ok() && b.ok());
  EXPECT_EQ(a->mesh.tets, b->mesh.tets);
  EXPECT_EQ(a->mesh.scalars, b->mesh.scalars);
  // Smaller than its arrays: the survivor deltas and counts repeat.
  EXPECT_LT(SerializeLevels(levels).size(), size_t(levels.collapses()) * 10);
}

TEST(LevelsFile, EveryTruncationIsRefused) {
  auto pm = MakePhantomMesh(12, 40);
  const std::string bytes = SerializeLevels(Record(pm.mesh, 0.5));
  ASSERT_TRUE(ParseLevels(bytes).ok());
  for (size_t n = 0; n < bytes.size(); ++n) {
    auto r = ParseLevels(bytes.substr(0, n), "cut.levels");
    ASSERT_FALSE(r.ok()) << "cut at " << n;
    EXPECT_EQ(r.status().code(), absl::StatusCode::kInvalidArgument) << n;
  }
}

TEST(LevelsFile, EveryFlippedByteIsRefused) {
  auto pm = MakePhantomMesh(12, 40);
  const std::string bytes = SerializeLevels(Record(pm.mesh, 0.5));
  for (size_t i = 0; i < bytes.size(); ++i) {
    std::string b = bytes;
    b[i] = char(b[i] ^ 0x20);
    EXPECT_FALSE(ParseLevels(b).ok()) << "byte " << i;
  }
}

// A header field changed and the checksum made right again (LevelsChecksum) reaches its own
// check: a writer with a bug, not a damaged file.
TEST(LevelsFile, WrongMagicVersionAndCountsAreRefusedWithWhatIsWrong) {
  auto pm = MakePhantomMesh(12, 40);
  const SimplifyLevels levels = Record(pm.mesh, 0.5);
  const std::string good = SerializeLevels(levels);
  auto sealed = [](std::string b) {
    b.resize(b.size() - 8);
    const uint64_t d = LevelsChecksum(b);
    b.append(reinterpret_cast<const char*>(&d), 8);
    return b;
  };
  ASSERT_EQ(sealed(good), good);
  std::string b = good;
  b[0] = 'X';
  ExpectRefused(sealed(b), "does not start with DECIMALV");
  b = good;
  Poke<uint32_t>(&b, 8, 2);
  ExpectRefused(sealed(b), "version 2, this reader knows version 1");
  b = good;
  Poke<uint32_t>(&b, 12, 4);
  ExpectRefused(sealed(b), "expected flags 0 or 1");
  b = good;
  Poke<uint64_t>(&b, 32, uint64_t(levels.base_vertices) + 1);
  ExpectRefused(sealed(b), "collapses <= vertices");
  b = good;
  Poke<uint64_t>(&b, 16, uint64_t{1} << 40);
  ExpectRefused(sealed(b), "expected vertices < 2^31");
  b = good;
  Poke<uint64_t>(&b, 32, uint64_t(levels.collapses()) + 1);
  ExpectRefused(sealed(b), "does not inflate");
  b = good;
  Poke<uint64_t>(&b, 56, uint64_t{5});
  ExpectRefused(sealed(b), "expected the file size less 72");
  b = good;
  Poke<uint64_t>(&b, 24, uint64_t{3});
  ExpectRefused(sealed(b), "the collapses delete");
  b = good;
  b[good.size() - 1] ^= 1;
  ExpectRefused(b, "checksum mismatch");
  ExpectRefused(std::string(10, 'D'), "shorter than the 72");
}

TEST(LevelsFile, ARecordIsRefusedForAnotherMeshOfTheSameSize) {
  auto pm = MakePhantomMesh(12, 40);
  const SimplifyLevels levels = Record(pm.mesh, 0.5);
  TetMesh other = pm.mesh;
  other.scalars[7] += 1;
  auto r = ExtractLevel(other, levels, 0.3);
  ASSERT_FALSE(r.ok());
  EXPECT_NE(std::string(r.status().message()).find("digest differs"), std::string::npos)
      << r.status();
}

}  // namespace
}  // namespace decima
