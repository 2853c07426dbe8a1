// Replays every seed of the fuzz corpora through the fuzz entry functions in the normal build,
// so the seeds (and the entries' contract checks) run on every ctest, not only under clang.
#include <algorithm>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include <gtest/gtest.h>

#include "core/mesh/mesh_io.h"
#include "core/render/transfer_function.h"
#include "tests/fuzz/fuzz_entries.h"
#include "tests/fuzz/fuzz_replay.h"

namespace decima::fuzz {
namespace {

TEST(FuzzReplay, EveryVtuSeedRunsThroughReadVtuEntry) { ReplayCorpus("vtu", ReadVtuEntry); }

TEST(FuzzReplay, EveryTransferFunctionSeedRunsThroughItsEntry) {
  ReplayCorpus("transfer_function", TransferFunctionEntry);
}

TEST(FuzzReplay, EveryNiftiSeedRunsThroughItsEntry) { ReplayCorpus("nifti", NiftiEntry); }
TEST(FuzzReplay, EveryMetaImageSeedRunsThroughItsEntry) {
  ReplayCorpus("metaimage", MetaImageEntry);
}
TEST(FuzzReplay, EveryNrrdSeedRunsThroughItsEntry) { ReplayCorpus("nrrd", NrrdEntry); }
// The volume corpora through the client's pre-upload header check: each seed's first byte (its
// layout bit) becomes VolumeHeaderEntry's selector of the same layout, so every NIfTI, MetaImage
// and NRRD seed is probed as the file it is; ok-* seeds (read by the readers) must be accepted.
TEST(FuzzReplay, EveryVolumeHeaderSeedRunsThroughItsEntry) {
  ReplayCorpus("volume_header", VolumeHeaderEntry);
}
// The same seeds from their own corpora (tests/fuzz/corpus/volume_header is a copy of them with
// the layout byte remapped, for the libFuzzer campaign).
TEST(FuzzReplay, EveryVolumeSeedRunsThroughTheClientHeaderCheck) {
  int ok = 0, seeds = 0;
  for (const auto& [corpus, first] :
       std::vector<std::pair<const char*, uint8_t>>{{"nifti", 0}, {"metaimage", 2}, {"nrrd", 4}}) {
    for (const fs::path& p : Seeds(corpus)) {
      SCOPED_TRACE(p.string());
      std::string b = Bytes(p);
      if (b.empty()) continue;
      b[0] = static_cast<char>(first + (b[0] & 1));
      VolumeHeaderEntry(reinterpret_cast<const uint8_t*>(b.data()), b.size());
      ++seeds;
      if (p.filename().string().rfind("ok-", 0) == 0) {
        EXPECT_TRUE(LastInputAccepted());
        ++ok;
      }
    }
  }
  EXPECT_GE(seeds, 25);
  EXPECT_GE(ok, 3);
}
TEST(FuzzReplay, EveryDicomSeedRunsThroughItsEntry) { ReplayCorpus("dicom", DicomEntry); }
TEST(FuzzReplay, EveryCheckpointSeedRunsThroughItsEntry) {
  ReplayCorpus("checkpoint", CheckpointEntry);
}
TEST(FuzzReplay, EveryLevelsSeedRunsThroughItsEntry) { ReplayCorpus("levels", LevelsEntry); }
TEST(FuzzReplay, EveryStreamWindowSeedRunsThroughItsEntry) {
  ReplayCorpus("stream_window", StreamWindowEntry);
}

// The corpus must keep files the readers accept (named ok-*), so the fuzzer starts past the
// header checks and the entries' invariant checks run on real meshes and functions.
TEST(FuzzReplay, SeedsNamedOkAreAccepted) {
  int ok = 0;
  for (const fs::path& p : Seeds("vtu")) {
    if (p.filename().string().rfind("ok-", 0) != 0) continue;
    ++ok;
    auto m = ReadVtu(p);
    EXPECT_TRUE(m.ok()) << p << ": " << m.status();
  }
  for (const fs::path& p : Seeds("transfer_function")) {
    if (p.filename().string().rfind("ok-", 0) != 0) continue;
    ++ok;
    auto tf = ParseTransferFunction(Bytes(p), ScalarRange{-1024, 3071});
    EXPECT_TRUE(tf.ok()) << p << ": " << tf.status();
  }
  EXPECT_GE(ok, 4);
}

TEST(FuzzReplay, VolumeSeedsNamedOkAreAccepted) {
  ExpectOkSeedsAccepted("nifti", NiftiEntry);
  ExpectOkSeedsAccepted("metaimage", MetaImageEntry);
  ExpectOkSeedsAccepted("nrrd", NrrdEntry);
  ExpectOkSeedsAccepted("dicom", DicomEntry);
  ExpectOkSeedsAccepted("checkpoint", CheckpointEntry);
  ExpectOkSeedsAccepted("levels", LevelsEntry);
  ExpectOkSeedsAccepted("stream_window", StreamWindowEntry);
}

}  // namespace
}  // namespace decima::fuzz
