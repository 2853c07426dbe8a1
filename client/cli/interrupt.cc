#include "client/cli/interrupt.h"

#include <signal.h>
#include <unistd.h>

#include <cstdio>
#include <cstring>

#include "client/cli/output.h"

namespace decima::client {

namespace {

// A signal handler reaches no context: the message is composed before it can run, in a fixed
// buffer that write(2) can print from the handler.
char interrupt_message[1024];

void OnInterrupt(int) {
  ssize_t n = ::write(2, interrupt_message, std::strlen(interrupt_message));
  (void)n;
  ::_exit(130);
}

void InstallHandler() {
  struct sigaction sa {};
  sa.sa_handler = OnInterrupt;
  sigemptyset(&sa.sa_mask);
  sigaction(SIGINT, &sa, nullptr);
}

}  // namespace

void ArmInterrupt(const CliContext& ctx, const std::string& job) {
  std::snprintf(interrupt_message, sizeof interrupt_message,
                "\ndecima: stopped watching %s; the job goes on on the server.\n"
                "  re-attach: %s\n  cancel it: %s\n",
                job.c_str(), ShellCommand(ctx, "watch", job).c_str(),
                ShellCommand(ctx, "cancel", job).c_str());
  InstallHandler();
}

void ArmInterruptMany(const CliContext& ctx, const std::vector<std::string>& names) {
  std::string ids;
  for (const auto& n : names) ids += " " + ShortId(n);
  std::string again = "decima ";
  if (ctx.flags.server != kDefaultServer) again += "--server " + ctx.flags.server + " ";
  again += "watch" + ids;
  std::snprintf(interrupt_message, sizeof interrupt_message,
                "\ndecima: stopped watching %zu jobs; they go on on the server.\n"
                "  re-attach: %s\n",
                names.size(), again.c_str());
  InstallHandler();
}

void DisarmInterrupt() { signal(SIGINT, SIG_DFL); }

}  // namespace decima::client
