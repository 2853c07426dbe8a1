// decima health: whether the server is serving (the standard health protocol).
#include "client/cli/output.h"
#include "client/cmd/commands.h"
#include "grpc/health/v1/health.grpc.pb.h"

namespace decima::client {

namespace {

int RunHealth(CliContext& ctx) {
  if (int rc = ConnectAndCheck(ctx, "health"); rc != kOk) return rc;
  auto stub = grpc::health::v1::Health::NewStub(ctx.conn.channel);
  grpc::health::v1::HealthCheckRequest req;
  grpc::health::v1::HealthCheckResponse resp;
  grpc::Status s = stub->Check(ctx.conn.Context().get(), req, &resp);
  if (!s.ok()) return Report(ctx, s, "health " + ctx.flags.server);
  std::string st = grpc::health::v1::HealthCheckResponse::ServingStatus_Name(resp.status());
  if (ctx.JsonOut()) {
    std::printf("{\"server\":%s,\"status\":\"%s\"}\n", JsonString(ctx.flags.server).c_str(),
                st.c_str());
  } else {
    std::printf("%s %s\n", ctx.flags.server.c_str(), st.c_str());
  }
  return resp.status() == grpc::health::v1::HealthCheckResponse::SERVING ? kOk : kUnavailable;
}

}  // namespace

Command NewCmdHealth(CLI::App& app, CliContext& ctx) {
  auto* cmd = app.add_subcommand("health", "check that the server is serving");
  AddOutputFlags(cmd, ctx.flags);
  return {cmd, [&ctx] { return RunHealth(ctx); }};
}

}  // namespace decima::client
