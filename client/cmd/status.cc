// decima status JOB (alias describe): the job as kubectl describe shows a resource.
#include "client/cli/describe.h"
#include "client/cli/output.h"
#include "client/cmd/commands.h"

namespace decima::client {

namespace {

struct StatusOptions {
  std::string job;
};

int RunStatus(CliContext& ctx, const StatusOptions& o) {
  if (int rc = ConnectAndCheck(ctx, "status"); rc != kOk) return rc;
  v1::Job job;
  if (int rc = GetJobOf(ctx, o.job, "status", &job); rc != kOk) return rc;
  if (ctx.JsonOut()) {
    std::printf("%s\n", ToJson(job).c_str());
  } else {
    DescribeJob(ctx, job);
  }
  return kOk;
}

}  // namespace

Command NewCmdStatus(CLI::App& app, CliContext& ctx) {
  auto o = std::make_shared<StatusOptions>();
  auto* cmd = app.add_subcommand("status", "describe a job: spec, input, times, result, artifacts");
  cmd->alias("describe");
  cmd->add_option("JOB", o->job, "job id, unique id prefix, or jobs/{id}")->required();
  AddOutputFlags(cmd, ctx.flags);
  return {cmd, [&ctx, o] { return RunStatus(ctx, *o); }};
}

}  // namespace decima::client
