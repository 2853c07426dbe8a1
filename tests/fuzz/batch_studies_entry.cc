// Fuzz entry of the CLI's batch study finder (client/batch.h): the folder a user hands to
// `decima submit DIR1 DIR2 ...` or `--each` is outside data, read by DCMTK up to group 0020.
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <set>
#include <string>
#include <string_view>

#include "client/batch.h"
#include "tests/fuzz/fuzz_entries.h"
#include "tests/fuzz/fuzz_require.h"

namespace decima::fuzz {

int BatchStudiesEntry(const uint8_t* data, size_t size) {
  namespace fs = std::filesystem;
  const fs::path dir =
      fs::temp_directory_path() / ("decima-batch-studies-fuzz-" + std::to_string(::getpid()));
  std::error_code ec;
  fs::remove_all(dir, ec);
  // Parts alternate between the folder and a subfolder, so the search below it is driven too.
  fs::create_directories(dir / "sub", ec);
  std::string_view in(reinterpret_cast<const char*>(data), size);
  std::set<std::string> written;
  for (int i = 0; i < 8; ++i) {
    const size_t at = in.find(kFileSeparator);
    const std::string_view part = in.substr(0, at);
    const fs::path path = (i % 2 == 0 ? dir : dir / "sub") / ("IM" + std::to_string(i));
    if (std::FILE* f = std::fopen(path.c_str(), "wb")) {
      if (!part.empty()) std::fwrite(part.data(), 1, part.size(), f);
      std::fclose(f);
    }
    written.insert(fs::relative(path, dir).generic_string());
    if (at == std::string_view::npos) break;
    in.remove_prefix(at + kFileSeparator.size());
  }
  std::vector<client::Study> studies;
  std::string error;
  const bool ok = client::FindStudies(dir, &studies, &error);
  Require(ok || !error.empty(), "a refused folder says why");
  SetLastInputAccepted(ok && !studies.empty());
  std::set<std::string> seen;
  for (const auto& s : studies) {
    // No volume file is written, so every study is a DICOM series of the files written here,
    // each file in one study only, each carrying the study's SeriesInstanceUID.
    Require(s.dicom(), "a study of this folder is a DICOM series");
    for (const auto& f : s.files) {
      Require(written.count(f.name) == 1, "a study's file is one of the folder's");
      Require(seen.insert(f.name).second, "a file belongs to one study");
      std::string uid, why;
      Require(client::ReadSeriesUid(f.path, &uid, &why) && uid == s.series_uid,
              "a study's files carry its SeriesInstanceUID");
    }
  }
  fs::remove_all(dir, ec);
  return 0;
}

}  // namespace decima::fuzz
