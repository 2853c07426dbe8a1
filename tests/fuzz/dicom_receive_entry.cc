// Fuzz entries of the DICOM receiver's parsing of received instances. DicomReceiveEntry: its
// handling of one received instance (DicomReceiver::StoreInstance, what the storage SCP calls for
// every C-STORE): the file a sender sent, its first 64 KiB read by DCMTK up to the pixel data, its
// UIDs and the AE titles checked, the file kept as a blob and recorded in a real SQLite job store.
// Every input gets fresh stores in a temporary folder of this process, removed afterwards, so
// nothing accumulates over a campaign. DicomSeriesCheckEntry: the settle loop's check of a series
// (CheckSeriesComplete) over the same bounded header reader.
#include <unistd.h>

#include <algorithm>
#include <array>
#include <filesystem>
#include <fstream>
#include <string>
#include <string_view>
#include <vector>

#include "absl/strings/str_split.h"
#include "server/dicom/dicom_receiver.h"
#include "server/files/blob_store.h"
#include "server/files/data_dir.h"
#include "server/store/job_store.h"
#include "server/util/sha256.h"
#include "tests/fuzz/fuzz_entries.h"
#include "tests/fuzz/fuzz_require.h"

namespace decima::fuzz {
namespace {

namespace fs = std::filesystem;

// DIMSE statuses StoreInstance answers (PS3.7 Annex C and PS3.4 B.2.3).
constexpr uint16_t kSuccess = 0x0000;
constexpr uint16_t kCannotUnderstand = 0xC000;
constexpr uint16_t kSopClassNotSupported = 0x0122;  // not a slice of a volume (SEG, SC, none)

// Calling AE titles a sender may present: the first two are AE titles (PS3.5 6.2: 1-16
// printable ASCII characters, no backslash), the others are not.
struct CallingAe {
  std::string title;
  bool valid;
};
const std::array<CallingAe, 7>& CallingAes() {
  static const std::array<CallingAe, 7> aes = {{{"FUZZ", true},
                                                {"PACS 01_x-y", true},
                                                {"", false},
                                                {"SEND\\ER", false},
                                                {"TAB\tAE", false},
                                                {"ABCDEFGHIJKLMNOPQ", false},
                                                {"SEND\xE4R", false}}};
  return aes;
}

// A DICOM UID as the receiver may record it: 1-64 characters of digits and dots.
bool LooksLikeUid(const std::string& s) {
  return !s.empty() && s.size() <= 64 &&
         std::all_of(s.begin(), s.end(), [](char c) { return (c >= '0' && c <= '9') || c == '.'; });
}

}  // namespace

int DicomReceiveEntry(const uint8_t* data, size_t size) {
  SetLastInputAccepted(false);
  static int counter = 0;
  const fs::path dir =
      fs::temp_directory_path() /
      ("decima-dicom-receive-fuzz-" + std::to_string(::getpid()) + "-" + std::to_string(counter++));
  std::error_code ec;
  fs::remove_all(dir, ec);
  fs::create_directories(dir);
  {
    const CallingAe& ae = CallingAes()[size > 0 ? data[0] % CallingAes().size() : 0];
    const uint8_t* bytes = size > 0 ? data + 1 : data;
    const size_t nbytes = size > 0 ? size - 1 : 0;
    const fs::path file = dir / "received.dcm";
    {
      std::ofstream out(file, std::ios::binary);
      out.write(reinterpret_cast<const char*>(bytes), static_cast<std::streamsize>(nbytes));
    }
    auto store = server::OpenSqliteJobStore((dir / "jobs.sqlite").string());
    Require(store.ok(), "the job store opens");
    auto blobs = server::LocalBlobStore::Open(dir / "blobs", /*fsync=*/false);
    Require(blobs.ok(), "the blob store opens");
    const server::DataDir data_dir(dir);
    server::DicomReceiverOptions options;
    options.min_free_mb = 0;  // the temp folder's free space is not what is fuzzed
    server::DicomReceiver receiver(options, &data_dir, store->get(), blobs->get(), nullptr,
                                   nullptr);
    std::string series;
    const uint16_t status = receiver.StoreInstance(file, ae.title, options.aet, &series);
    Require(status == kSuccess || status == kCannotUnderstand || status == kSopClassNotSupported,
            "an instance is stored, or refused as not understood or as no slice of a volume "
            "(nothing else fails here)");
    auto kept = (*store)->ListDicomInstances();
    Require(kept.ok(), "the received instances list");
    if (status == kSuccess) {
      Require(ae.valid, "an instance from a calling AE that is no AE title is refused");
      Require(kept->size() == 1, "a stored instance is one row of the job store");
      const server::DicomInstanceRecord& row = kept->front();
      Require(row.series_instance_uid == series, "the row holds the series the caller was told");
      Require(LooksLikeUid(row.series_instance_uid) && LooksLikeUid(row.sop_instance_uid),
              "the recorded UIDs are DICOM UIDs");
      Require(row.calling_ae == ae.title && row.called_ae == options.aet,
              "the row holds the association's AE titles");
      auto sha = server::Sha256OfFile(file);
      Require(sha.ok() && row.sha256 == *sha, "the row names the blob of the received bytes");
      Require((*blobs)->Has(row.sha256), "the received bytes are kept as that blob");
      SetLastInputAccepted(true);
    } else {
      Require(kept->empty(), "a refused instance leaves no row");
      int64_t files_in_blobs = 0;
      for (const auto& e : fs::recursive_directory_iterator(dir / "blobs", ec)) {
        files_in_blobs += e.is_regular_file();
      }
      Require(files_in_blobs == 0, "a refused instance leaves no blob");
      Require(series.empty(), "a refused instance names no series");
    }
  }
  fs::remove_all(dir, ec);
  return 0;
}

int DicomSeriesCheckEntry(const uint8_t* data, size_t size) {
  SetLastInputAccepted(false);
  static int counter = 0;
  const fs::path dir =
      fs::temp_directory_path() /
      ("decima-dicom-series-fuzz-" + std::to_string(::getpid()) + "-" + std::to_string(counter++));
  std::error_code ec;
  fs::remove_all(dir, ec);
  fs::create_directories(dir);
  {
    const absl::string_view bytes(reinterpret_cast<const char*>(data), size);
    std::vector<fs::path> files;
    const absl::string_view separator(kFileSeparator.data(), kFileSeparator.size());
    for (absl::string_view part : absl::StrSplit(bytes, absl::ByString(separator))) {
      if (files.size() == 4) break;  // a few slices reach every branch
      files.push_back(dir / ("i" + std::to_string(files.size()) + ".dcm"));
      std::ofstream out(files.back(), std::ios::binary);
      out.write(part.data(), static_cast<std::streamsize>(part.size()));
    }
    const absl::Status st = server::CheckSeriesComplete(files);
    Require(st.ok() || st.code() == absl::StatusCode::kInvalidArgument,
            "a series is complete or INVALID_ARGUMENT says why");
    Require(!st.ok() || files.size() >= 2, "a complete series has two slices or more");
    std::vector<fs::path> reversed(files.rbegin(), files.rend());
    Require(server::CheckSeriesComplete(reversed).ok() == st.ok(),
            "the order the instances arrived in does not change the verdict");
    SetLastInputAccepted(st.ok());
  }
  fs::remove_all(dir, ec);
  return 0;
}

}  // namespace decima::fuzz
