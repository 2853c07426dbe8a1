// decima watch JOB...: one job with its bar and summary, several at once with one table.
#include "client/cli/watch.h"

#include "client/batch.h"
#include "client/cmd/commands.h"

namespace decima::client {

namespace {

struct WatchOptions {
  std::vector<std::string> jobs;
};

int RunWatch(CliContext& ctx, const WatchOptions& o) {
  if (int rc = ConnectAndCheck(ctx, "watch"); rc != kOk) return rc;
  if (o.jobs.size() == 1) {
    std::string name;
    if (int rc = ResolveJob(ctx, o.jobs[0], &name); rc != kOk) return rc;
    v1::Job final;
    return Watch(ctx, name, &final);
  }
  std::vector<std::string> names(o.jobs.size());
  for (size_t i = 0; i < o.jobs.size(); ++i) {
    if (int rc = ResolveJob(ctx, o.jobs[i], &names[i]); rc != kOk) return rc;
  }
  const std::vector<WatchOutcome> outcomes = WatchMany(ctx, names);
  std::vector<StudyRow> rows;
  std::vector<int> codes;
  for (size_t i = 0; i < names.size(); ++i) {
    StudyRow row;
    row.job = names[i];
    const v1::Volume* vol = GetVolume(ctx, outcomes[i].final.spec().volume());
    row.input = vol != nullptr ? vol->display_name() : outcomes[i].final.spec().volume();
    SetOutcome(outcomes[i], &row);
    codes.push_back(row.rc);
    rows.push_back(std::move(row));
  }
  PrintStudyTable(ctx, rows);
  PrintStudyCounts(ctx, rows, /*jobs=*/true);
  return BatchExitCode(codes);
}

}  // namespace

Command NewCmdWatch(CLI::App& app, CliContext& ctx) {
  auto o = std::make_shared<WatchOptions>();
  auto* cmd = app.add_subcommand(
      "watch", "stream a job's progress until it ends (several jobs: all at once, one table)");
  cmd->add_option("JOB", o->jobs, "job ids, unique id prefixes, or jobs/{id}")->required();
  AddOutputFlags(cmd, ctx.flags);
  return {cmd, [&ctx, o] { return RunWatch(ctx, *o); }};
}

}  // namespace decima::client
