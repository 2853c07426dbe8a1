// Replays the corpora of the server's fuzz entries (Upload, CreateVolume, DICOM receive)
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
TEST(FuzzReplay, EveryDicomReceiveSeedRunsThroughItsEntry) {
  ReplayCorpus("dicom_receive", DicomReceiveEntry);
}
TEST(FuzzReplay, ServerSeedsNamedOkAreAccepted) {
  ExpectOkSeedsAccepted("upload", UploadEntry);
  ExpectOkSeedsAccepted("create_volume", CreateVolumeEntry);
  ExpectOkSeedsAccepted("dicom_receive", DicomReceiveEntry);
}

}  // namespace
}  // namespace decima::fuzz
