// Replays the corpora of the server's request-handling fuzz entries (Upload, CreateVolume)
// through them in the normal build (gRPC on a loopback port over real stores in a temp folder).
#include <gtest/gtest.h>

#include "tests/fuzz/fuzz_entries.h"
#include "tests/fuzz/fuzz_replay.h"

namespace decima::fuzz {
namespace {

TEST(FuzzReplay, EveryUploadSeedRunsThroughItsEntry) { ReplayCorpus("upload", UploadEntry); }
TEST(FuzzReplay, EveryCreateVolumeSeedRunsThroughItsEntry) {
  ReplayCorpus("create_volume", CreateVolumeEntry);
}
TEST(FuzzReplay, ServerSeedsNamedOkAreAccepted) {
  ExpectOkSeedsAccepted("upload", UploadEntry);
  ExpectOkSeedsAccepted("create_volume", CreateVolumeEntry);
}

}  // namespace
}  // namespace decima::fuzz
