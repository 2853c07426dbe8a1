// decima delete JOB... [--volume] (alias rm): finished jobs with their artifacts, and with
// --volume their input volumes when no other job uses them.
#include "client/cli/output.h"
#include "client/cmd/commands.h"

namespace decima::client {

namespace {

struct DeleteOptions {
  std::vector<std::string> jobs;
  bool with_volume = false;
};

int RunDelete(CliContext& ctx, const DeleteOptions& o) {
  if (int rc = ConnectAndCheck(ctx, "delete"); rc != kOk) return rc;
  auto jobs = v1::Jobs::NewStub(ctx.conn.channel);
  int64_t freed = 0;
  std::set<std::string> vols;
  for (const auto& arg : o.jobs) {
    std::string name;
    if (int rc = ResolveJob(ctx, arg, &name); rc != kOk) return rc;
    v1::GetJobRequest greq;
    greq.set_name(name);
    v1::Job job;
    grpc::Status s = jobs->GetJob(ctx.conn.Context().get(), greq, &job);
    if (!s.ok()) return Report(ctx, s, "delete " + name);
    v1::DeleteJobRequest dreq;
    dreq.set_name(name);
    v1::DeleteJobResponse dresp;
    s = jobs->DeleteJob(ctx.conn.Context().get(), dreq, &dresp);
    if (!s.ok()) return Report(ctx, s, "delete " + name);
    const int64_t bytes = SummarizeJob(job, 0).artifact_bytes;
    freed += bytes;
    if (ctx.JsonOut()) {
      std::printf("{\"deleted\":%s,\"bytes\":%lld}\n", JsonString(name).c_str(),
                  static_cast<long long>(bytes));
    } else {
      std::printf("deleted %s (%s of artifacts)\n", name.c_str(), FormatBytes(bytes).c_str());
    }
    vols.insert(job.spec().volume());
    if (!job.spec().label_map().empty()) vols.insert(job.spec().label_map());
  }
  if (o.with_volume) {
    if (int rc = DeleteUnusedVolumes(ctx, vols, false, &freed); rc != kOk) return rc;
  }
  if (!ctx.Quiet()) std::fprintf(stderr, "decima: freed %s\n", FormatBytes(freed).c_str());
  return kOk;
}

}  // namespace

int DeleteUnusedVolumes(CliContext& ctx, const std::set<std::string>& candidates, bool dry_run,
                        int64_t* freed) {
  auto volumes = v1::Volumes::NewStub(ctx.conn.channel);
  std::vector<v1::Job> remaining;
  if (int rc = ListAllJobs(ctx, {}, &remaining); rc != kOk) return rc;
  std::set<std::string> used;
  for (const auto& j : remaining) {
    used.insert(j.spec().volume());
    if (!j.spec().label_map().empty()) used.insert(j.spec().label_map());
  }
  for (const auto& v : candidates) {
    if (used.count(v) != 0) continue;
    const v1::Volume* vol = GetVolume(ctx, v);
    if (vol == nullptr) continue;
    if (!dry_run) {
      v1::DeleteVolumeRequest dreq;
      dreq.set_name(v);
      v1::DeleteVolumeResponse dresp;
      grpc::Status s = volumes->DeleteVolume(ctx.conn.Context().get(), dreq, &dresp);
      if (!s.ok()) return Report(ctx, s, "delete " + v);
    }
    *freed += vol->size_bytes();
    if (ctx.JsonOut()) {
      std::printf("{\"deleted\":%s,\"dry_run\":%s,\"bytes\":%lld}\n", JsonString(v).c_str(),
                  dry_run ? "true" : "false", static_cast<long long>(vol->size_bytes()));
    } else {
      std::printf("%s%s (%s, %s)\n", dry_run ? "would delete " : "deleted ", v.c_str(),
                  TerminalSafe(vol->display_name()).c_str(),
                  FormatBytes(vol->size_bytes()).c_str());
    }
  }
  return kOk;
}

Command NewCmdDelete(CLI::App& app, CliContext& ctx) {
  auto o = std::make_shared<DeleteOptions>();
  auto* cmd = app.add_subcommand("delete", "delete finished jobs with their artifacts");
  cmd->alias("rm");
  cmd->add_option("JOB", o->jobs, "job ids, unique id prefixes, or jobs/{id}")->required();
  cmd->add_flag("--volume", o->with_volume,
                "also delete each job's input volume when no other job uses it");
  AddOutputFlags(cmd, ctx.flags);
  return {cmd, [&ctx, o] { return RunDelete(ctx, *o); }};
}

}  // namespace decima::client
