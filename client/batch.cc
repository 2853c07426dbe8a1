#include "client/batch.h"

#include <dcmtk/dcmdata/dcdeftag.h>
#include <dcmtk/dcmdata/dcfilefo.h>
#include <dcmtk/oflog/oflog.h>

#include <algorithm>
#include <cctype>
#include <fstream>
#include <map>
#include <mutex>

#include "client/text.h"

namespace decima::client {
namespace fs = std::filesystem;
namespace {

// The "DICM" marker at byte 128 of a Part 10 file; DICOMDIR (an index of a medium) is no image.
bool IsDicomFile(const fs::path& path) {
  if (AsciiLower(path.filename().string()) == "dicomdir") return false;
  std::ifstream in(path, std::ios::binary);
  char magic[132] = {};
  return in.read(magic, sizeof magic) && std::string(magic + 128, 4) == "DICM";
}

// "...45.6789": the tail that tells series of one study apart in a narrow table.
std::string UidTail(const std::string& uid) {
  if (uid.size() <= 12) return uid;
  std::string tail = uid.substr(uid.size() - 9);
  if (tail[0] == '.') tail.erase(0, 1);
  return "..." + tail;
}

}  // namespace

bool IsVolumeFileName(const std::string& file_name) {
  const std::string n = AsciiLower(file_name);
  for (const char* ext : {".nii", ".nii.gz", ".mha", ".mhd", ".nrrd", ".nhdr"}) {
    if (EndsWith(n, ext) && n.size() > std::string(ext).size()) return true;
  }
  return false;
}

bool ReadSeriesUid(const fs::path& file, std::string* uid, std::string* error) {
  // DCMTK logs parse warnings to stderr by default; the caller reports the outcome itself.
  static std::once_flag quiet;
  std::call_once(quiet, [] { OFLog::configure(OFLogger::FATAL_LOG_LEVEL); });
  DcmFileFormat ff;
  // Parsing stops at (0020,000F), so a large pixel data element is never read.
  const OFCondition st =
      ff.loadFileUntilTag(file.c_str(), EXS_Unknown, EGL_noChange, DCM_MaxReadLength,
                          ERM_autoDetect, DcmTagKey(0x0020, 0x000F));
  if (st.bad()) {
    *error = file.string() + ": not a readable DICOM file (" + st.text() + ")";
    return false;
  }
  OFString value;
  uid->clear();
  if (ff.getDataset()->findAndGetOFString(DCM_SeriesInstanceUID, value).good()) {
    *uid = value.c_str();
  }
  return true;
}

bool FindStudies(const fs::path& source, std::vector<Study>* studies, std::string* error) {
  studies->clear();
  std::error_code ec;
  if (fs::is_regular_file(source, ec)) {
    Study s;
    s.source = source;
    s.label = source.string();
    s.display_name = source.filename().string();
    s.input = source;
    studies->push_back(std::move(s));
    return true;
  }
  if (!fs::is_directory(source, ec)) {
    *error = source.string() + ": no such file or folder";
    return false;
  }
  std::vector<InputFile> all;
  if (!CollectInputs(source, &all, error)) {
    // An empty folder is no error here: it holds no study, which the caller reports.
    if (error->find("holds no files") != std::string::npos) {
      error->clear();
      return true;
    }
    return false;
  }
  std::map<std::string, std::vector<InputFile>> series;  // by SeriesInstanceUID, sorted
  for (auto& f : all) {
    if (IsVolumeFileName(f.path.filename().string())) {
      Study s;
      s.source = source;
      s.label = (source / f.name).string();
      s.display_name = f.path.filename().string();
      s.input = f.path;
      studies->push_back(std::move(s));
    } else if (IsDicomFile(f.path)) {
      std::string uid;
      if (!ReadSeriesUid(f.path, &uid, error)) return false;
      series[uid].push_back(std::move(f));
    }
  }
  const std::string folder = source.filename().empty() ? source.parent_path().filename().string()
                                                       : source.filename().string();
  for (auto& [uid, files] : series) {
    Study s;
    s.source = source;
    s.input = source;
    s.series_uid = uid;
    s.label = source.string() + " (series " + (uid.empty() ? "without UID" : UidTail(uid)) + ", " +
              std::to_string(files.size()) + " files)";
    // One series keeps the folder's name, as `decima submit DIR` names it; several are told
    // apart by their UID's tail.
    s.display_name = series.size() == 1 ? folder : folder + " " + UidTail(uid);
    s.files = std::move(files);
    studies->push_back(std::move(s));
  }
  return true;
}

bool EachEntry(const fs::path& folder, std::vector<fs::path>* entries, std::string* error) {
  entries->clear();
  std::error_code ec;
  if (!fs::is_directory(folder, ec)) {
    *error = "--each " + folder.string() + ": not a folder";
    return false;
  }
  for (auto it = fs::directory_iterator(folder, ec); !ec && it != fs::directory_iterator();
       it.increment(ec)) {
    const std::string name = it->path().filename().string();
    if (name.rfind('.', 0) == 0) continue;
    // Subfolders are searched; of the files only volumes are studies (notes, checksums and the
    // data files of .mhd/.nhdr headers beside them are not).
    std::error_code type_ec;
    if (it->is_directory(type_ec) || IsVolumeFileName(name)) entries->push_back(it->path());
  }
  if (ec) {
    *error = "--each " + folder.string() + ": " + ec.message();
    return false;
  }
  std::sort(entries->begin(), entries->end());
  return true;
}

int BatchExitCode(const std::vector<int>& codes) {
  auto any = [&](int c) { return std::find(codes.begin(), codes.end(), c) != codes.end(); };
  for (int c : {static_cast<int>(kJobFailed), static_cast<int>(kJobCancelled),
                static_cast<int>(kTargetNotReached)}) {
    if (any(c)) return c;
  }
  for (int c : codes) {
    if (c != kOk) return c;
  }
  return kOk;
}

std::string ArtifactFolderName(const std::string& label, std::vector<std::string>* taken) {
  std::string base;
  for (char c : label) {
    const bool keep =
        std::isalnum(static_cast<unsigned char>(c)) || c == '.' || c == '_' || c == '-';
    base += keep ? c : '_';
  }
  // A leading dot would hide the folder; an all-dots name would be "." or "..".
  while (!base.empty() && base[0] == '.') base[0] = '_';
  if (base.empty()) base = "study";
  std::string name = base;
  for (int n = 2; std::find(taken->begin(), taken->end(), name) != taken->end(); ++n) {
    name = base + "-" + std::to_string(n);
  }
  taken->push_back(name);
  return name;
}

}  // namespace decima::client
