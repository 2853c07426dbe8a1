// decima series [--page-size N] [--page-token T] [--all]: the history of the server's DICOM
// C-STORE receiver; `series delete SERIES_UID [--from AE]` removes a series' waiting instances.
#include "client/cli/output.h"
#include "client/cmd/commands.h"

namespace decima::client {

namespace {

struct SeriesOptions {
  int page_size = 50;
  std::string page_token;
  bool all = false;
  CLI::App* delete_cmd = nullptr;
  std::string delete_uid, delete_from;
};

int RunSeriesDelete(CliContext& ctx, const SeriesOptions& o) {
  auto volumes = v1::Volumes::NewStub(ctx.conn.channel);
  v1::DeleteReceivedSeriesRequest req;
  req.set_series_instance_uid(o.delete_uid);
  req.set_calling_ae(o.delete_from);
  v1::DeleteReceivedSeriesResponse resp;
  // Not retried: a delete that reached the server and lost its answer finds nothing the second
  // time (NOT_FOUND), which would hide that it worked.
  grpc::Status s = volumes->DeleteReceivedSeries(ctx.conn.Context().get(), req, &resp);
  if (!s.ok()) return Report(ctx, s, "series delete " + o.delete_uid);
  if (ctx.JsonOut()) {
    std::printf("%s\n", ToJson(resp).c_str());
  } else {
    std::printf("deleted %d waiting instance(s) of series %s (%s freed)\n",
                resp.deleted_instances(), o.delete_uid.c_str(),
                FormatBytes(resp.freed_bytes()).c_str());
  }
  return kOk;
}

std::vector<std::string> SeriesRow(const v1::ReceivedSeries& r, bool wide) {
  // The UID's tail tells series apart; -o wide or json shows it whole.
  const std::string& uid = r.series_instance_uid();
  std::string state = v1::ReceivedSeries::State_Name(r.state());
  // The job and, when it failed or the receive was closed by another, why.
  std::string what = r.job().empty()      ? r.reason()
                     : r.reason().empty() ? ShortId(r.job())
                                          : ShortId(r.job()) + ": " + r.reason();
  std::vector<std::string> row = {
      wide || uid.size() <= 24 ? uid : "..." + uid.substr(uid.size() - 21),
      r.calling_ae(),
      r.called_ae(),
      std::to_string(r.instance_count()),
      state,
      what.empty() ? "-" : (wide ? what : what.substr(0, 100)),
      FormatTime(r.first_receive_time()),
      FormatTime(r.last_receive_time())};
  if (wide) {
    row.insert(row.end(), {r.route().empty() ? "-" : r.route(), r.owner(),
                           r.association_id().empty() ? "-" : r.association_id(),
                           r.send_status().empty() ? "-" : r.send_status()});
  }
  return row;
}

int RunSeries(CliContext& ctx, const SeriesOptions& o) {
  if (int rc = ConnectAndCheck(ctx, "series"); rc != kOk) return rc;
  if (*o.delete_cmd) return RunSeriesDelete(ctx, o);
  auto volumes = v1::Volumes::NewStub(ctx.conn.channel);
  v1::ListReceivedSeriesRequest req;
  req.set_page_size(o.page_size);
  req.set_page_token(o.page_token);
  const bool wide = ctx.Wide();
  std::vector<std::vector<std::string>> rows = {
      {"SERIES", "FROM", "TO", "INSTANCES", "STATE", "JOB / REASON", "FIRST", "LAST"}};
  if (wide) rows[0].insert(rows[0].end(), {"ROUTE", "OWNER", "ASSOCIATION", "RESULTS"});
  for (int page = 0; page < 1000; ++page) {
    v1::ListReceivedSeriesResponse resp;
    grpc::Status s = WithRetry(
        ctx, [&] { return volumes->ListReceivedSeries(ctx.conn.Context().get(), req, &resp); });
    if (!s.ok()) return Report(ctx, s, "series");
    for (const auto& r : resp.received_series()) {
      if (ctx.JsonOut()) {
        std::printf("%s\n", ToJson(r).c_str());
      } else {
        rows.push_back(SeriesRow(r, wide));
      }
    }
    if (!ContinueListing(ctx, resp.next_page_token(), o.all)) break;
    req.set_page_token(resp.next_page_token());
  }
  if (!ctx.JsonOut()) {
    if (rows.size() == 1) {
      std::fprintf(stderr, "decima: no series received\n");
    } else {
      PrintTable(rows);
    }
  }
  return kOk;
}

}  // namespace

Command NewCmdSeries(CLI::App& app, CliContext& ctx) {
  auto o = std::make_shared<SeriesOptions>();
  auto* cmd = app.add_subcommand(
      "series", "list the series the server received by DICOM C-STORE and what became of them");
  cmd->add_option("--page-size", o->page_size, "series per page")->capture_default_str();
  cmd->add_option("--page-token", o->page_token, "continue a listing");
  cmd->add_flag("--all", o->all, "follow every page");
  AddOutputFlags(cmd, ctx.flags);
  o->delete_cmd = cmd->add_subcommand(
      "delete",
      "remove a received series' waiting instances (not yet in a job) and free their blobs");
  o->delete_cmd->add_option("SERIES_UID", o->delete_uid, "the SeriesInstanceUID")->required();
  o->delete_cmd->add_option("--from", o->delete_from,
                            "only the instances sent by this calling AE title (default: every "
                            "sender's you may delete)");
  return {cmd, [&ctx, o] { return RunSeries(ctx, *o); }};
}

}  // namespace decima::client
