// decima retry JOB [--watch]: queues a failed or cancelled job again.
#include "client/cli/output.h"
#include "client/cli/watch.h"
#include "client/cmd/commands.h"

namespace decima::client {

namespace {

struct RetryOptions {
  std::string job;
  bool watch = false;
};

int RunRetry(CliContext& ctx, const RetryOptions& o) {
  if (int rc = ConnectAndCheck(ctx, "retry"); rc != kOk) return rc;
  auto jobs = v1::Jobs::NewStub(ctx.conn.channel);
  v1::RetryJobRequest req;
  if (int rc = ResolveJob(ctx, o.job, req.mutable_name()); rc != kOk) return rc;
  v1::Job job;
  grpc::Status s = jobs->RetryJob(ctx.conn.Context().get(), req, &job);
  if (!s.ok()) return Report(ctx, s, "retry " + req.name());
  PrintJobLine(ctx, job);
  if (!o.watch) return kOk;
  v1::Job final;
  return Watch(ctx, job.name(), &final);
}

}  // namespace

Command NewCmdRetry(CLI::App& app, CliContext& ctx) {
  auto o = std::make_shared<RetryOptions>();
  auto* cmd = app.add_subcommand("retry", "queue a failed or cancelled job again");
  cmd->add_option("JOB", o->job, "job id, unique id prefix, or jobs/{id}")->required();
  cmd->add_flag("--watch", o->watch, "watch the job until it ends");
  AddOutputFlags(cmd, ctx.flags);
  return {cmd, [&ctx, o] { return RunRetry(ctx, *o); }};
}

}  // namespace decima::client
