// ChildProcess: the exit status comes back, Terminate(grace) asks politely and then kills, and
// the protocol descriptor reaches the child.
#include "server/jobs/child_process.h"

#include <poll.h>
#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <cerrno>
#include <chrono>
#include <filesystem>

namespace decima::server {
namespace {

namespace fs = std::filesystem;
using namespace std::chrono_literals;

ChildOptions Shell(const std::string& script) {
  ChildOptions o;
  o.argv = {"/bin/sh", "-c", script};
  o.log = fs::temp_directory_path() / ("decima-child-test-" + std::to_string(::getpid()) + ".log");
  return o;
}

// Whether one byte arrived on `fd` within `timeout`.
bool WaitForReadyByte(int fd, std::chrono::milliseconds timeout) {
  const auto deadline = std::chrono::steady_clock::now() + timeout;
  for (;;) {
    const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(
        deadline - std::chrono::steady_clock::now());
    if (left.count() <= 0) return false;
    pollfd p{fd, POLLIN, 0};
    const int n = ::poll(&p, 1, static_cast<int>(left.count()));
    if (n < 0 && errno == EINTR) continue;
    if (n <= 0) return false;
    char byte = 0;
    return ::read(fd, &byte, 1) == 1;
  }
}

TEST(ChildProcess, ReportsTheExitCodeAndWritesTheProtocolFd) {
  auto child = ChildProcess::Spawn(Shell("printf hello >&3; exit 7"));
  ASSERT_TRUE(child.ok()) << child.status();
  char buf[16] = {};
  ssize_t n = 0, got = 0;
  while ((n = ::read((*child)->fd(), buf + got, sizeof buf - 1 - got)) > 0) got += n;
  EXPECT_STREQ(buf, "hello");
  const int st = (*child)->Wait();
  ASSERT_TRUE(WIFEXITED(st));
  EXPECT_EQ(WEXITSTATUS(st), 7);
  EXPECT_EQ(DescribeWaitStatus(st), "exited with code 7");
}

TEST(ChildProcess, TerminateEndsAPoliteChildWithSigterm) {
  auto child = ChildProcess::Spawn(Shell("exec sleep 30"));
  ASSERT_TRUE(child.ok());
  (*child)->Terminate(5s);
  const int st = (*child)->Wait();
  ASSERT_TRUE(WIFSIGNALED(st));
  EXPECT_EQ(WTERMSIG(st), SIGTERM);
}

TEST(ChildProcess, TerminateKillsAChildThatIgnoresSigtermAfterTheGrace) {
  // An ignored signal stays ignored across exec: the sleep ignores TERM. The byte on the
  // protocol pipe says the trap is installed (a TERM before it would end the shell politely).
  auto child = ChildProcess::Spawn(Shell("trap '' TERM; printf r >&3; exec sleep 30"));
  ASSERT_TRUE(child.ok());
  ASSERT_TRUE(WaitForReadyByte((*child)->fd(), 10s)) << "the child never said it was ready";
  const auto t0 = std::chrono::steady_clock::now();
  (*child)->Terminate(200ms);
  (*child)->Terminate(10s);  // a later request does not postpone the kill
  const int st = (*child)->Wait();
  const auto took = std::chrono::steady_clock::now() - t0;
  ASSERT_TRUE(WIFSIGNALED(st));
  EXPECT_EQ(WTERMSIG(st), SIGKILL);
  EXPECT_GE(took, 200ms);
  EXPECT_LT(took, 5s);
  EXPECT_THAT(DescribeWaitStatus(st), ::testing::HasSubstr("signal 9"));
}

TEST(ChildProcess, AMissingExecutableExitsWith127) {
  ChildOptions o = Shell("");
  o.argv = {"/nonexistent/decima-child"};
  auto child = ChildProcess::Spawn(o);
  ASSERT_TRUE(child.ok());
  const int st = (*child)->Wait();
  ASSERT_TRUE(WIFEXITED(st));
  EXPECT_EQ(WEXITSTATUS(st), 127);
}

}  // namespace
}  // namespace decima::server
