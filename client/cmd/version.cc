// decima version: the client's version, and whether the server answers (at most 2 s: the
// client's version is the answer, the server an extra; no fail-fast check before it).
#include "client/cli/output.h"
#include "client/cmd/commands.h"
#include "grpc/health/v1/health.grpc.pb.h"

#ifndef DECIMA_VERSION
#define DECIMA_VERSION "unknown"
#endif

namespace decima::client {

namespace {

int RunVersion(CliContext& ctx) {
  if (int rc = Connect(ctx); rc != kOk) return rc;
  auto stub = grpc::health::v1::Health::NewStub(ctx.conn.channel);
  grpc::health::v1::HealthCheckRequest req;
  grpc::health::v1::HealthCheckResponse resp;
  auto call = ctx.conn.Context();
  call->set_deadline(
      std::chrono::system_clock::now() +
      std::chrono::milliseconds(static_cast<int64_t>(std::min(2.0, ctx.flags.timeout_s) * 1000)));
  grpc::Status s = stub->Check(call.get(), req, &resp);
  if (ctx.JsonOut()) {
    std::printf("{\"client\":%s,\"server\":%s,\"server_reachable\":%s}\n",
                JsonString(DECIMA_VERSION).c_str(), JsonString(ctx.flags.server).c_str(),
                s.ok() ? "true" : "false");
  } else {
    std::printf("decima %s\nserver %s %s\n", DECIMA_VERSION, ctx.flags.server.c_str(),
                s.ok() ? "reachable" : "unreachable");
  }
  return kOk;
}

}  // namespace

Command NewCmdVersion(CLI::App& app, CliContext& ctx) {
  auto* cmd = app.add_subcommand("version", "print the client's version and the server's");
  AddOutputFlags(cmd, ctx.flags);
  return {cmd, [&ctx] { return RunVersion(ctx); }};
}

}  // namespace decima::client
