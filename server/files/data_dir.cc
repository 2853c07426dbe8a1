#include "server/files/data_dir.h"

#include <fstream>
#include <sstream>

#include <algorithm>
#include <vector>

#include "absl/strings/numbers.h"
#include "absl/strings/str_cat.h"

namespace decima::server {
namespace fs = std::filesystem;

namespace {

// The claim epochs with a folder under jobs/<id>/attempts/.
std::vector<int64_t> Attempts(const fs::path& attempts) {
  std::vector<int64_t> out;
  std::error_code ec;
  for (fs::directory_iterator it(attempts, ec), end; !ec && it != end; it.increment(ec)) {
    int64_t epoch = 0;
    if (absl::SimpleAtoi(it->path().filename().string(), &epoch)) out.push_back(epoch);
  }
  return out;
}

}  // namespace

absl::Status DataDir::ResetJobOut(const std::string& id, int64_t epoch) const {
  std::error_code ec;
  for (int64_t e : Attempts(job_dir(id) / "attempts")) {
    if (e != epoch) fs::remove_all(job_attempt(id, e), ec);
  }
  fs::remove_all(job_out(id, epoch), ec);
  ec.clear();
  fs::create_directories(job_out(id, epoch), ec);
  if (ec) {
    return absl::InternalError(
        absl::StrCat("creating ", job_out(id, epoch).string(), ": ", ec.message()));
  }
  return absl::OkStatus();
}

int64_t DataDir::LatestAttempt(const std::string& id) const {
  int64_t latest = 0;
  for (int64_t e : Attempts(job_dir(id) / "attempts")) latest = std::max(latest, e);
  return latest;
}

std::filesystem::path DataDir::ArtifactsDir(const std::string& id) const {
  const int64_t latest = LatestAttempt(id);
  return latest > 0 ? job_out(id, latest) : job_dir(id) / "out";
}

void DataDir::RemoveAttempt(const std::string& id, int64_t epoch) const {
  std::error_code ec;
  fs::remove_all(job_attempt(id, epoch), ec);
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

void DataDir::RemoveJobOut(const std::string& id, int64_t epoch) const {
  std::error_code ec;
  fs::remove_all(job_out(id, epoch), ec);
}

void DataDir::RemoveJobCheckpoints(const std::string& id) const {
  std::error_code ec;
  fs::remove_all(job_checkpoints(id), ec);
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
