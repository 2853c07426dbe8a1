#include "server/data_dir.h"

#include <fstream>
#include <sstream>

#include "absl/strings/str_cat.h"

namespace decima::server {
namespace fs = std::filesystem;

absl::Status DataDir::ResetJobOut(const std::string& id) const {
  std::error_code ec;
  fs::remove_all(job_out(id), ec);
  fs::create_directories(job_out(id), ec);
  if (ec)
    return absl::InternalError(absl::StrCat("creating ", job_out(id).string(), ": ", ec.message()));
  return absl::OkStatus();
}

absl::Status DataDir::WriteFileAtomically(const fs::path& path, const std::string& bytes) const {
  std::error_code ec;
  fs::create_directories(path.parent_path(), ec);
  const fs::path tmp = path.string() + ".tmp";
  {
    std::ofstream out(tmp, std::ios::binary | std::ios::trunc);
    out << bytes;
    if (!out.good()) return absl::InternalError(absl::StrCat("writing ", tmp.string()));
  }
  fs::rename(tmp, path, ec);
  if (ec) return absl::InternalError(absl::StrCat("renaming ", tmp.string(), ": ", ec.message()));
  return absl::OkStatus();
}

std::string DataDir::ReadJobFault(const std::string& id) const {
  std::ifstream in(job_fault(id), std::ios::binary);
  if (!in) return {};
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

void DataDir::RemoveJobOut(const std::string& id) const {
  std::error_code ec;
  fs::remove_all(job_out(id), ec);
}

void DataDir::RemoveJob(const std::string& id) const {
  std::error_code ec;
  fs::remove_all(job_dir(id), ec);
}

void DataDir::RemoveVolume(const std::string& id) const {
  std::error_code ec;
  fs::remove_all(volume_dir(id), ec);
}

}  // namespace decima::server
