// decima cancel JOB: cancels, then waits (within --timeout) until the job stopped.
#include <thread>

#include "client/cli/output.h"
#include "client/cmd/commands.h"

namespace decima::client {

namespace {

struct CancelOptions {
  std::string job;
};

int RunCancel(CliContext& ctx, const CancelOptions& o) {
  if (int rc = ConnectAndCheck(ctx, "cancel"); rc != kOk) return rc;
  auto jobs = v1::Jobs::NewStub(ctx.conn.channel);
  v1::CancelJobRequest req;
  if (int rc = ResolveJob(ctx, o.job, req.mutable_name()); rc != kOk) return rc;
  v1::Job job;
  grpc::Status s = jobs->CancelJob(ctx.conn.Context().get(), req, &job);
  if (!s.ok()) return Report(ctx, s, "cancel " + req.name());
  // Cancel is best effort: wait (within the call timeout) until the job reached a final state.
  auto until = std::chrono::steady_clock::now() +
               std::chrono::milliseconds(static_cast<int64_t>(ctx.flags.timeout_s * 1000));
  while (job.state() == v1::RUNNING || job.state() == v1::QUEUED) {
    if (std::chrono::steady_clock::now() > until) {
      PrintJobLine(ctx, job);
      return kTimeout;
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    v1::GetJobRequest greq;
    greq.set_name(req.name());
    s = jobs->GetJob(ctx.conn.Context().get(), greq, &job);
    if (!s.ok()) return Report(ctx, s, "status " + req.name());
  }
  PrintJobLine(ctx, job);
  return kOk;
}

}  // namespace

Command NewCmdCancel(CLI::App& app, CliContext& ctx) {
  auto o = std::make_shared<CancelOptions>();
  auto* cmd = app.add_subcommand("cancel", "cancel a job (waits until it stopped)");
  cmd->add_option("JOB", o->job, "job id, unique id prefix, or jobs/{id}")->required();
  AddOutputFlags(cmd, ctx.flags);
  return {cmd, [&ctx, o] { return RunCancel(ctx, *o); }};
}

}  // namespace decima::client
