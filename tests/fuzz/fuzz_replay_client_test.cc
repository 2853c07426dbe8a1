// Replays the dicom corpus through the CLI's batch study finder (BatchStudiesEntry) in the
// normal build: its seeds are DICOM folders, which is what a batch searches.
#include <gtest/gtest.h>

#include "tests/fuzz/fuzz_entries.h"
#include "tests/fuzz/fuzz_replay.h"

namespace decima::fuzz {
namespace {

TEST(FuzzReplay, EveryDicomSeedRunsThroughTheBatchStudyFinder) {
  ReplayCorpus("dicom", BatchStudiesEntry);
}

// A folder the DICOM reader accepts (ok-*) holds at least one study for a batch.
TEST(FuzzReplay, DicomSeedsNamedOkAreStudiesOfABatch) {
  int ok = 0;
  for (const fs::path& p : Seeds("dicom")) {
    if (p.filename().string().rfind("ok-", 0) != 0) continue;
    SCOPED_TRACE(p.string());
    const std::string b = Bytes(p);
    BatchStudiesEntry(reinterpret_cast<const uint8_t*>(b.data()), b.size());
    EXPECT_TRUE(LastInputAccepted());
    ++ok;
  }
  EXPECT_GE(ok, 2);
}

}  // namespace
}  // namespace decima::fuzz
