// decima: the command-line client of decima-server. Data on stdout, progress on stderr.
// The verbs live in client/cmd/ (one file each), what they share in client/cli/.
#include <unistd.h>

#include <CLI/CLI.hpp>

#include "client/cli/context.h"
#include "client/cmd/commands.h"

#ifndef DECIMA_VERSION
#define DECIMA_VERSION "unknown"
#endif

using namespace decima::client;

namespace {

const char* kExitCodes = R"(
Exit codes:
  0 success            1 error              2 usage
  3 job failed         4 job cancelled      5 timeout (deadline exceeded)
  6 not found          7 not authenticated, or permission denied
  8 server unavailable (also: TLS handshake refused)
  10 job succeeded but the reduction target was not reached (see the warning)
Several studies (submit DIR1 DIR2 ..., submit --each FOLDER, watch JOB1 JOB2 ...): 0 only
when every study succeeded; else 3 if any failed (its job FAILED, or its input was refused
before a job was made), else 4 if any was cancelled, else 10 if any stopped short of its
target. A folder with no volume in it is reported and skipped; it does not change the code.

Environment: DECIMA_SERVER (default 127.0.0.1:50051), DECIMA_TOKEN, DECIMA_TIMEOUT,
DECIMA_CA_CERT, DECIMA_TLS_CERT, DECIMA_TLS_KEY.)";

}  // namespace

int main(int argc, char** argv) {
  CliContext ctx;
  ctx.stderr_tty = ::isatty(2) != 0;
  CLI::App app{
      "decima: submit medical volumes to a decima-server, watch the jobs, fetch the "
      "meshes and images"};
  app.footer(kExitCodes);
  app.require_subcommand(1);
  app.set_version_flag("--version", std::string("decima ") + DECIMA_VERSION);
  AddGlobalFlags(app, ctx.flags);
  // In the order --help lists them.
  const Command commands[] = {
      NewCmdSubmit(app, ctx), NewCmdWatch(app, ctx),   NewCmdStatus(app, ctx),
      NewCmdList(app, ctx),   NewCmdCancel(app, ctx),  NewCmdRetry(app, ctx),
      NewCmdFetch(app, ctx),  NewCmdDelete(app, ctx),  NewCmdPrune(app, ctx),
      NewCmdHealth(app, ctx), NewCmdVersion(app, ctx), NewCmdPull(app, ctx),
      NewCmdSeries(app, ctx),
  };
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e) == 0 ? kOk : kUsage;
  }
  for (const Command& c : commands) {
    if (*c.app) return c.run();
  }
  return kUsage;
}
