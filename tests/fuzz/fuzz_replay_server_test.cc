// Replays the corpora of the server's fuzz entries (Upload, CreateVolume, DICOM receive and
// series check) through them in the normal build (gRPC on a loopback port over real stores in a
// temp folder).
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
TEST(FuzzReplay, EveryDicomSeriesCheckSeedRunsThroughItsEntry) {
  ReplayCorpus("dicom_series_check", DicomSeriesCheckEntry);
}
TEST(FuzzReplay, ServerSeedsNamedOkAreAccepted) {
  ExpectOkSeedsAccepted("upload", UploadEntry);
  ExpectOkSeedsAccepted("create_volume", CreateVolumeEntry);
  ExpectOkSeedsAccepted("dicom_receive", DicomReceiveEntry);
  ExpectOkSeedsAccepted("dicom_series_check", DicomSeriesCheckEntry);
}

}  // namespace
}  // namespace decima::fuzz
