// Framing of the job child's messages (server/worker.proto): each message is its size as a
// base-128 varint followed by its bytes, the format of protobuf's delimited_message_util. The
// reader side is incremental because the server polls the pipe with a timeout (to renew the
// lease and watch for cancel) and a read may end anywhere inside a message.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

#include "absl/status/status.h"
#include "server/jobs/worker.pb.h"

namespace decima::server {

// Frames larger than this are refused: metrics_json is a few KiB, progress a few hundred bytes.
inline constexpr uint64_t kMaxFrameBytes = uint64_t{64} << 20;

// Writes one frame to `fd` (blocking, retried on EINTR). Internal error if the pipe is gone.
absl::Status WriteFrame(int fd, const worker::WorkerMessage& message);

// Accumulates bytes read from the child and hands out complete messages in order.
// Not thread-safe: one reader thread.
class FrameReader {
 public:
  void Append(const char* data, size_t size) { buffer_.append(data, size); }
  // True with *out set when a whole frame is buffered; false when more bytes are needed.
  // A frame that does not parse, or is larger than kMaxFrameBytes, makes status() an error
  // and every later call return false (the child is then treated as crashed).
  bool Next(worker::WorkerMessage* out);
  const absl::Status& status() const { return status_; }
  // Bytes held that do not form a whole frame yet (non-zero at EOF: a truncated message).
  size_t pending() const { return buffer_.size() - start_; }

 private:
  std::string buffer_;
  size_t start_ = 0;
  absl::Status status_;
};

}  // namespace decima::server
