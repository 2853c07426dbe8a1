#include "server/jobs/child_process.h"

#include <fcntl.h>
#include <signal.h>
#include <sys/prctl.h>
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <thread>

#include "absl/strings/str_cat.h"

namespace decima::server {

absl::StatusOr<std::unique_ptr<ChildProcess>> ChildProcess::Spawn(const ChildOptions& o) {
  if (o.argv.empty()) return absl::InvalidArgumentError("ChildProcess: empty argv");
  // Everything the child needs is prepared before fork: after it, only async-signal-safe calls.
  std::vector<std::string> args = o.argv;
  std::vector<char*> argv;
  for (auto& a : args) argv.push_back(a.data());
  argv.push_back(nullptr);
  int p[2];
  if (::pipe2(p, O_CLOEXEC) != 0) {
    return absl::InternalError(absl::StrCat("pipe: ", std::strerror(errno)));
  }
  const int log = ::open(o.log.c_str(), O_WRONLY | O_CREAT | O_APPEND | O_CLOEXEC, 0644);
  const int devnull = ::open("/dev/null", O_RDONLY | O_CLOEXEC);
  const pid_t parent = ::getpid();
  rlimit mem{};
  mem.rlim_cur = mem.rlim_max = static_cast<rlim_t>(o.memory_mb) << 20;
  const int proto_fd = o.protocol_fd;
  const pid_t pid = ::fork();
  if (pid == 0) {
    ::prctl(PR_SET_PDEATHSIG, SIGKILL);  // the server died: so does its job
    if (::getppid() != parent) ::_exit(127);
    sigset_t none;
    sigemptyset(&none);
    ::sigprocmask(SIG_SETMASK, &none, nullptr);
    if (devnull >= 0) ::dup2(devnull, 0);
    if (log >= 0) {
      ::dup2(log, 1);
      ::dup2(log, 2);
    }
    if (p[1] == proto_fd) {
      ::fcntl(proto_fd, F_SETFD, 0);
    } else {
      ::dup2(p[1], proto_fd);  // dup2 clears FD_CLOEXEC on the copy
    }
    if (o.memory_mb > 0) ::setrlimit(RLIMIT_AS, &mem);
    ::execv(argv[0], argv.data());
    ::_exit(127);
  }
  const int err = errno;
  ::close(p[1]);
  if (log >= 0) ::close(log);
  if (devnull >= 0) ::close(devnull);
  if (pid < 0) {
    ::close(p[0]);
    return absl::InternalError(absl::StrCat("fork: ", std::strerror(err)));
  }
  return std::unique_ptr<ChildProcess>(new ChildProcess(pid, p[0]));
}

ChildProcess::~ChildProcess() {
  CloseFd();
  if (!status_) {
    ::kill(pid_, SIGKILL);
    int st;
    while (::waitpid(pid_, &st, 0) < 0 && errno == EINTR) {
    }
  }
}

void ChildProcess::CloseFd() {
  if (fd_ >= 0) ::close(fd_);
  fd_ = -1;
}

void ChildProcess::Terminate(std::chrono::milliseconds grace) {
  if (term_sent_ || status_) return;
  ::kill(pid_, SIGTERM);
  term_sent_ = true;
  kill_at_ = std::chrono::steady_clock::now() + grace;
}

void ChildProcess::Escalate() {
  if (term_sent_ && !kill_sent_ && std::chrono::steady_clock::now() >= kill_at_) {
    ::kill(pid_, SIGKILL);
    kill_sent_ = true;
  }
}

std::optional<int> ChildProcess::TryWait() {
  if (status_) return status_;
  int st = 0;
  pid_t r = ::waitpid(pid_, &st, WNOHANG);
  if (r == pid_) {
    status_ = st;
    return status_;
  }
  if (r < 0 && errno != EINTR) {
    // Not our child any more (cannot happen unless someone else reaped it): treat as gone.
    status_ = 0;
    return status_;
  }
  Escalate();
  return std::nullopt;
}

int ChildProcess::Wait() {
  for (;;) {
    if (auto st = TryWait()) return *st;
    std::this_thread::sleep_for(std::chrono::milliseconds(5));
  }
}

std::string DescribeWaitStatus(int wstatus) {
  if (WIFEXITED(wstatus)) return absl::StrCat("exited with code ", WEXITSTATUS(wstatus));
  if (WIFSIGNALED(wstatus)) {
    const int sig = WTERMSIG(wstatus);
    const char* d = ::strsignal(sig);
    return absl::StrCat("was killed by signal ", sig, " (", d ? d : "?", ")");
  }
  return absl::StrCat("ended with wait status ", wstatus);
}

}  // namespace decima::server
