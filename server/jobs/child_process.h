// A child process with a protocol pipe: spawn, one Terminate(grace) (SIGTERM now, SIGKILL once
// the grace period passed), reap. The only place the server forks.
//
// The child dies with the server (PR_SET_PDEATHSIG), starts with no blocked signals (the server
// blocks SIGTERM in its threads), reads /dev/null, appends stdout and stderr to a log file and
// writes its protocol on `protocol_fd`. Thread-safety: one owner thread.
#pragma once

#include <sys/types.h>

#include <chrono>
#include <filesystem>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "absl/status/statusor.h"

namespace decima::server {

struct ChildOptions {
  std::vector<std::string> argv;  // argv[0] is the executable's path
  std::filesystem::path log;      // stdout and stderr are appended here
  int protocol_fd = 3;            // the child's end of the pipe, as this descriptor
  int64_t memory_mb = 0;          // RLIMIT_AS of the child; 0 = unlimited
};

class ChildProcess {
 public:
  // INTERNAL if the pipe or fork fails (the message says which, with errno).
  static absl::StatusOr<std::unique_ptr<ChildProcess>> Spawn(const ChildOptions& options);
  ~ChildProcess();  // a child still running is killed (SIGKILL) and reaped

  ChildProcess(const ChildProcess&) = delete;
  ChildProcess& operator=(const ChildProcess&) = delete;

  pid_t pid() const { return pid_; }
  // Read end of the protocol pipe; -1 after CloseFd.
  int fd() const { return fd_; }
  void CloseFd();

  // SIGTERM now; SIGKILL when TryWait or Wait runs after `grace`. Later calls keep the first
  // deadline, so a cancel and a shutdown arriving together do not postpone the kill.
  void Terminate(std::chrono::milliseconds grace);
  bool terminating() const { return term_sent_; }

  // The wait status once the child exited (reaped), else nullopt; escalates a due Terminate.
  std::optional<int> TryWait();
  // Blocks until the child exited, escalating a due Terminate; returns the wait status.
  int Wait();

 private:
  ChildProcess(pid_t pid, int fd) : pid_(pid), fd_(fd) {}
  void Escalate();

  pid_t pid_;
  int fd_;
  std::optional<int> status_;
  bool term_sent_ = false;
  bool kill_sent_ = false;
  std::chrono::steady_clock::time_point kill_at_{};
};

// "exited with code 2", "was killed by signal 9 (Killed)".
std::string DescribeWaitStatus(int wstatus);

}  // namespace decima::server
