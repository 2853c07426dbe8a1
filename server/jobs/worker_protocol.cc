#include "server/jobs/worker_protocol.h"

#include <unistd.h>

#include <cerrno>
#include <cstring>

#include "absl/strings/str_cat.h"

namespace decima::server {

absl::Status WriteFrame(int fd, const worker::WorkerMessage& message) {
  const std::string body = message.SerializeAsString();
  std::string frame;
  frame.reserve(body.size() + 10);
  uint64_t n = body.size();
  while (n >= 0x80) {
    frame.push_back(static_cast<char>((n & 0x7f) | 0x80));
    n >>= 7;
  }
  frame.push_back(static_cast<char>(n));
  frame += body;
  const char* p = frame.data();
  size_t left = frame.size();
  while (left > 0) {
    ssize_t w = ::write(fd, p, left);
    if (w < 0) {
      if (errno == EINTR) continue;
      return absl::InternalError(absl::StrCat("writing a worker message: ", std::strerror(errno)));
    }
    p += w;
    left -= static_cast<size_t>(w);
  }
  return absl::OkStatus();
}

bool FrameReader::Next(worker::WorkerMessage* out) {
  if (!status_.ok()) return false;
  // Varint size.
  uint64_t size = 0;
  size_t pos = start_;
  for (int shift = 0;; shift += 7) {
    if (pos >= buffer_.size()) return false;
    if (shift > 63) {
      status_ = absl::DataLossError("worker message: malformed size");
      return false;
    }
    const auto byte = static_cast<unsigned char>(buffer_[pos++]);
    size |= uint64_t{byte & 0x7fu} << shift;
    if ((byte & 0x80) == 0) break;
  }
  if (size > kMaxFrameBytes) {
    status_ = absl::DataLossError(absl::StrCat("worker message of ", size, " bytes"));
    return false;
  }
  if (buffer_.size() - pos < size) return false;
  if (!out->ParseFromArray(buffer_.data() + pos, static_cast<int>(size))) {
    status_ = absl::DataLossError("worker message does not parse");
    return false;
  }
  start_ = pos + size;
  // Drop consumed bytes once they dominate, so the buffer does not grow with the job.
  if (start_ > 4096 && start_ * 2 > buffer_.size()) {
    buffer_.erase(0, start_);
    start_ = 0;
  }
  return true;
}

}  // namespace decima::server
