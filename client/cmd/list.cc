// decima list (alias ls): the jobs as a table, newest first; -o wide, -o json, paging.
#include "client/cli/output.h"
#include "client/cmd/commands.h"

namespace decima::client {

namespace {

struct ListOptions {
  std::vector<std::string> states;
  int page_size = 50;
  std::string page_token;
  bool all = false;
};

int RunList(CliContext& ctx, const ListOptions& o) {
  if (int rc = ConnectAndCheck(ctx, "list"); rc != kOk) return rc;
  auto jobs = v1::Jobs::NewStub(ctx.conn.channel);
  v1::ListJobsRequest req;
  for (const auto& st : o.states) {
    v1::JobState v;
    if (!ParseJobState(st, &v)) {
      std::fprintf(stderr,
                   "decima: --state %s: not one of queued, running, succeeded, failed, cancelled\n",
                   st.c_str());
      return kUsage;
    }
    req.add_states(v);
  }
  req.set_page_size(o.page_size);
  req.set_page_token(o.page_token);
  const bool wide = ctx.Wide();
  std::vector<std::vector<std::string>> rows = {JobHeader(wide)};
  for (int page = 0; page < 1000; ++page) {
    v1::ListJobsResponse resp;
    grpc::Status s =
        WithRetry(ctx, [&] { return jobs->ListJobs(ctx.conn.Context().get(), req, &resp); });
    if (!s.ok()) return Report(ctx, s, "list");
    for (const auto& j : resp.jobs()) {
      if (ctx.JsonOut()) {
        std::printf("%s\n", ToJson(j).c_str());
      } else {
        rows.push_back(JobRow(ctx, j, wide));
      }
    }
    if (!ContinueListing(ctx, resp.next_page_token(), o.all)) break;
    req.set_page_token(resp.next_page_token());
  }
  if (!ctx.JsonOut()) {
    if (rows.size() == 1) {
      std::fprintf(stderr, "decima: no jobs%s\n", o.states.empty() ? "" : " in these states");
    } else {
      PrintTable(rows);
    }
  }
  return kOk;
}

}  // namespace

Command NewCmdList(CLI::App& app, CliContext& ctx) {
  auto o = std::make_shared<ListOptions>();
  auto* cmd = app.add_subcommand("list", "list jobs as a table, newest first");
  cmd->alias("ls");
  cmd->add_option("--state", o->states,
                  "only these states (queued, running, succeeded, failed, cancelled; any case)")
      ->delimiter(',');
  cmd->add_option("--page-size", o->page_size, "jobs per page")->capture_default_str();
  cmd->add_option("--page-token", o->page_token, "continue a listing");
  cmd->add_flag("--all", o->all, "follow every page");
  AddOutputFlags(cmd, ctx.flags);
  return {cmd, [&ctx, o] { return RunList(ctx, *o); }};
}

}  // namespace decima::client
