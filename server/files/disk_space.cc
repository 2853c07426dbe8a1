#include "server/files/disk_space.h"

#include <fcntl.h>
#include <sys/statvfs.h>
#include <unistd.h>

#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "spdlog/spdlog.h"

namespace decima::server {
namespace fs = std::filesystem;

std::string HumanBytes(int64_t bytes) {
  if (bytes < 0) return "unknown";
  if (bytes < (int64_t{1} << 10)) return absl::StrCat(bytes, " bytes");
  const char* units[] = {"KB", "MB", "GB", "TB"};
  double v = static_cast<double>(bytes) / 1024.0;
  int u = 0;
  while (v >= 1024.0 && u < 3) {
    v /= 1024.0;
    ++u;
  }
  // Two calls, not a chosen format: clang checks absl::StrFormat's format at compile time.
  return v < 10 ? absl::StrFormat("%.1f %s", v, units[u]) : absl::StrFormat("%.0f %s", v, units[u]);
}

DiskSpace::DiskSpace(fs::path root, int64_t reserve_bytes)
    : root_(std::move(root)), reserve_bytes_(reserve_bytes > 0 ? reserve_bytes : 0) {}

int64_t DiskSpace::Free() const {
  struct statvfs st {};
  if (::statvfs(root_.c_str(), &st) != 0) return -1;
  return static_cast<int64_t>(st.f_bavail) * static_cast<int64_t>(st.f_frsize);
}

absl::Status DiskSpace::Admit(int64_t bytes, const std::string& what) const {
  const int64_t free = Free();
  if (free < 0 || bytes <= free) return absl::OkStatus();
  return absl::ResourceExhaustedError(absl::StrCat(
      what, " needs ", HumanBytes(bytes), " (", bytes, " bytes) but the server's disk has ",
      HumanBytes(free), " (", free, " bytes) free; delete jobs or volumes, or ask the operator"));
}

void DiskSpace::BeforeDelete() {
  if (reserve_bytes_ == 0) return;
  std::lock_guard<std::mutex> lock(mu_);
  if (Free() >= reserve_bytes_) return;
  std::error_code ec;
  if (fs::remove(reserve_file(), ec)) {
    spdlog::warn("disk nearly full ({} free): released the {} reserve so deletes can proceed",
                 HumanBytes(Free()), HumanBytes(reserve_bytes_));
  }
}

bool DiskSpace::Refill() {
  if (reserve_bytes_ == 0) return true;
  std::lock_guard<std::mutex> lock(mu_);
  std::error_code ec;
  if (fs::file_size(reserve_file(), ec) == static_cast<uintmax_t>(reserve_bytes_)) return true;
  if (Free() < 2 * reserve_bytes_) return false;
  const fs::path tmp = root_ / "reserve.tmp";
  const int fd = ::open(tmp.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0600);
  if (fd < 0) return false;
  const int rc = ::posix_fallocate(fd, 0, reserve_bytes_);
  ::close(fd);
  if (rc != 0) {
    fs::remove(tmp, ec);
    return false;
  }
  fs::rename(tmp, reserve_file(), ec);
  return !ec;
}

}  // namespace decima::server
