#include "tests/testing/process.h"

#include <fcntl.h>
#include <netinet/in.h>
#include <signal.h>
#include <spawn.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <thread>

namespace decima::testing {

int FreePort() {
  const int s = ::socket(AF_INET, SOCK_STREAM, 0);
  if (s < 0) return 0;
  sockaddr_in a{};
  a.sin_family = AF_INET;
  a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  a.sin_port = 0;
  socklen_t len = sizeof a;
  int port = 0;
  if (::bind(s, reinterpret_cast<sockaddr*>(&a), sizeof a) == 0 &&
      ::getsockname(s, reinterpret_cast<sockaddr*>(&a), &len) == 0) {
    port = ntohs(a.sin_port);
  }
  ::close(s);
  return port;
}

namespace {

// posix_spawn, not fork + exec: the tests that start programs are multi-threaded (gRPC,
// client threads), and after fork in such a process only async-signal-safe calls are allowed.
// Code of ours between fork and exec (opening files, building argv, setenv: malloc and libc
// locks another thread may hold at the fork) can leave the child hung before exec. glibc's
// posix_spawn runs no user code in the child and does the redirections itself.
pid_t SpawnWith(const std::vector<std::string>& argv, const std::string& out,
                const std::string& err, int out_flags,
                const std::map<std::string, std::string>& env) {
  std::vector<char*> args;
  for (const auto& a : argv) args.push_back(const_cast<char*>(a.c_str()));
  args.push_back(nullptr);
  // The inherited environment with `env` replacing or adding names.
  std::vector<std::string> vars;
  for (char** e = environ; *e != nullptr; ++e) {
    const std::string var = *e;
    if (env.count(var.substr(0, var.find('='))) == 0) vars.push_back(var);
  }
  for (const auto& [name, value] : env) vars.push_back(name + "=" + value);
  std::vector<char*> envp;
  for (auto& v : vars) envp.push_back(v.data());
  envp.push_back(nullptr);

  posix_spawn_file_actions_t actions;
  posix_spawn_file_actions_init(&actions);
  posix_spawn_file_actions_addopen(&actions, 0, "/dev/null", O_RDONLY, 0);
  posix_spawn_file_actions_addopen(&actions, 1, out.c_str(), O_WRONLY | O_CREAT | out_flags, 0644);
  if (err == out) {
    posix_spawn_file_actions_adddup2(&actions, 1, 2);
  } else {
    posix_spawn_file_actions_addopen(&actions, 2, err.c_str(), O_WRONLY | O_CREAT | out_flags,
                                     0644);
  }
  pid_t pid = -1;
  const int rc = ::posix_spawn(&pid, args[0], &actions, nullptr, args.data(), envp.data());
  posix_spawn_file_actions_destroy(&actions);
  return rc == 0 ? pid : -1;
}

}  // namespace

pid_t Spawn(const std::vector<std::string>& argv, const std::string& log) {
  return SpawnWith(argv, log, log, O_APPEND, {});
}

pid_t Spawn(const std::vector<std::string>& argv, const std::string& out, const std::string& err,
            const std::map<std::string, std::string>& env) {
  return SpawnWith(argv, out, err, O_TRUNC, env);
}

std::string ProcessState(pid_t pid) {
  const std::filesystem::path proc = "/proc/" + std::to_string(pid);
  std::error_code ec;
  std::string text = "exe " + std::filesystem::read_symlink(proc / "exe", ec).string();
  auto first_line = [](const std::filesystem::path& p) {
    std::ifstream in(p);
    std::string line;
    std::getline(in, line);
    return line;
  };
  {
    std::ifstream in(proc / "status");
    for (std::string line; std::getline(in, line);) {
      if (line.rfind("State:", 0) == 0) text += ", " + line;
    }
  }
  text += ", threads waiting in:";
  int shown = 0;
  for (const auto& task : std::filesystem::directory_iterator(proc / "task", ec)) {
    if (++shown > 16) break;
    text += " " + first_line(task.path() / "wchan");
  }
  return text;
}

int WaitExit(pid_t pid, std::chrono::seconds timeout, std::string* at_timeout) {
  if (pid <= 0) return 127;  // never waitpid(-1): that would reap any child of the test
  const auto until = std::chrono::steady_clock::now() + timeout;
  for (;;) {
    int st = 0;
    pid_t r = ::waitpid(pid, &st, WNOHANG);
    if (r == pid) return WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
    if (r < 0) return -1;
    if (std::chrono::steady_clock::now() > until) {
      if (at_timeout != nullptr) *at_timeout = ProcessState(pid);
      ::kill(pid, SIGKILL);
      ::waitpid(pid, &st, 0);
      return -1;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
  }
}

}  // namespace decima::testing
