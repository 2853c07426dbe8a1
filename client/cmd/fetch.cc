// decima fetch JOB --out DIR [--only NAME...] [--reduction R]: a succeeded job's artifacts,
// resumed and checked (size, sha256); also the download of `submit --out`. With --reduction,
// the mesh at R from the job's level record: a level job (spec.levels_of) is queued, watched
// and its artifacts fetched.
#include <algorithm>
#include <fstream>
#include <optional>

#include "client/cli/output.h"
#include "client/cli/watch.h"
#include "client/cmd/commands.h"
#include "client/text.h"
#include "decima/v1/jobs.grpc.pb.h"

namespace decima::client {

namespace fs = std::filesystem;

namespace {

struct FetchOptions {
  std::string job;
  fs::path out;
  std::vector<std::string> only;
  std::optional<double> reduction;
};

// Whether `file` is one of `only`: a file name, or a kind (as in --outputs) that produces it.
bool MatchesOnly(const std::string& file, const std::vector<std::string>& only) {
  if (only.empty()) return true;
  for (const std::string& listed : only) {
    const std::string o = AsciiLower(listed);
    if (o == file) return true;
    if (o == "vtu" && file == "mesh.vtu") return true;
    if (o == "msh" && file == "mesh.msh") return true;
    if (o == "medit" && file == "mesh.mesh") return true;
    if (o == "glb" && file == "surfaces.glb") return true;
    if (o == "levels" && file == "mesh.levels") return true;
    if (o == "stl" && file.rfind("surface-", 0) == 0 && file.size() > 4 &&
        file.compare(file.size() - 4, 4, ".stl") == 0) {
      return true;
    }
    if (o == "labels" && file == "labels.nii.gz") return true;
    if (o == "segmentation" && file == "segmentation.png") return true;
    if (o == "report" && file == "report.html") return true;
    if (o == "curve" && file == "curve.png") return true;
    if (o == "metrics" && file == "metrics.json") return true;
    if (o == "images" && file.size() > 4 && file.compare(file.size() - 4, 4, ".png") == 0 &&
        file != "segmentation.png" && file != "curve.png") {
      return true;
    }
  }
  return false;
}

}  // namespace

int FetchArtifacts(CliContext& ctx, const v1::Job& job, const fs::path& out,
                   const std::vector<std::string>& only) {
  if (job.state() != v1::SUCCEEDED) {
    std::fprintf(stderr, "decima: fetch %s: the job is %s%s%s\n", job.name().c_str(),
                 v1::JobState_Name(job.state()).c_str(), job.error().message().empty() ? "" : ": ",
                 TerminalSafe(job.error().message()).c_str());
    int code = ExitCodeFor(job.state());
    return code == kOk ? kError : code;
  }
  // Every name given must select something, so a typo is an error and not an empty fetch.
  for (const auto& o : only) {
    bool any = false;
    for (const auto& a : job.artifacts()) any = any || MatchesOnly(a.file_name(), {o});
    if (!any) {
      std::string names;
      for (const auto& a : job.artifacts()) names += " " + a.file_name();
      std::fprintf(stderr,
                   "decima: fetch --only %s: no such artifact in %s; it has:%s (or the kinds "
                   "vtu, msh, medit, stl, glb, labels, images, segmentation, report, curve, "
                   "metrics)\n",
                   o.c_str(), job.name().c_str(), names.c_str());
      return kUsage;
    }
  }
  int64_t total = 0;
  for (const auto& a : job.artifacts()) {
    if (!MatchesOnly(a.file_name(), only)) continue;
    fs::path path;
    grpc::Status s = WithRetry(ctx, [&] {
      return DownloadArtifact(
          ctx.conn, a, out,
          [&](int64_t d, int64_t t) { ByteBar(ctx, "fetch " + a.file_name(), d, t); }, &path);
    });
    if (!s.ok()) return Report(ctx, s, "fetch " + a.name());
    total += a.size_bytes();
    if (ctx.JsonOut()) {
      std::printf("{\"artifact\":%s,\"path\":%s,\"size_bytes\":%lld}\n",
                  JsonString(a.file_name()).c_str(), JsonString(path.string()).c_str(),
                  static_cast<long long>(a.size_bytes()));
    } else {
      std::printf("%s\n", path.c_str());
    }
  }
  if (!job.metrics_json().empty() && MatchesOnly("metrics.json", only) &&
      !fs::exists(out / "metrics.json")) {
    std::ofstream(out / "metrics.json") << job.metrics_json();
  }
  if (!ctx.Quiet())
    std::fprintf(stderr, "decima: fetched %s into %s\n", FormatBytes(total).c_str(), out.c_str());
  std::fflush(stdout);
  return kOk;
}

namespace {

// The level job of `parent` at `reduction`: its outputs are the mesh kinds --only names (the
// mesh.vtu alone when it names none), its pictures drawn as the parent's were.
v1::CreateJobRequest LevelJobRequest(const v1::Job& parent, double reduction,
                                     const std::vector<std::string>& only) {
  v1::CreateJobRequest req;
  v1::JobSpec* spec = req.mutable_spec();
  spec->set_levels_of(parent.name());
  spec->set_target_reduction(reduction);
  // The kinds a level job writes (its mesh comes from a record: no "levels", no "curve").
  static const std::vector<std::string> kLevelKinds = {
      "vtu", "msh", "medit", "stl", "glb", "labels", "images", "segmentation", "report"};
  for (const std::string& given : only) {
    const std::string o = AsciiLower(given);
    const bool kind = std::find(kLevelKinds.begin(), kLevelKinds.end(), o) != kLevelKinds.end();
    const bool listed =
        std::find(spec->outputs().begin(), spec->outputs().end(), o) != spec->outputs().end();
    if (kind && !listed) spec->add_outputs(o);
  }
  if (spec->outputs().empty()) spec->add_outputs("vtu");
  *spec->mutable_views() = parent.spec().views();
  if (parent.spec().has_image_size()) spec->set_image_size(parent.spec().image_size());
  spec->set_transfer_function(parent.spec().transfer_function());
  req.set_request_id(NewRequestId());
  return req;
}

int FetchLevel(CliContext& ctx, const v1::Job& parent, const FetchOptions& o) {
  const v1::CreateJobRequest req = LevelJobRequest(parent, *o.reduction, o.only);
  auto jobs = v1::Jobs::NewStub(ctx.conn.channel);
  v1::Job job;
  grpc::Status s =
      WithRetry(ctx, [&] { return jobs->CreateJob(ctx.conn.Context().get(), req, &job); });
  if (!s.ok()) return Report(ctx, s, "fetch " + parent.name() + " --reduction");
  if (!ctx.Quiet()) {
    std::fprintf(stderr, "decima: the level %g of %s is taken from its record by %s\n",
                 *o.reduction, parent.name().c_str(), job.name().c_str());
  }
  v1::Job final;
  const int rc = Watch(ctx, job.name(), &final);
  if (rc != kOk && rc != kTargetNotReached) return rc;
  const int frc = FetchArtifacts(ctx, final, o.out, o.only);
  return frc != kOk ? frc : rc;
}

int RunFetch(CliContext& ctx, const FetchOptions& o) {
  if (int rc = ConnectAndCheck(ctx, "fetch"); rc != kOk) return rc;
  v1::Job job;
  if (int rc = GetJobOf(ctx, o.job, "fetch", &job); rc != kOk) return rc;
  if (o.reduction) return FetchLevel(ctx, job, o);
  return FetchArtifacts(ctx, job, o.out, o.only);
}

}  // namespace

Command NewCmdFetch(CLI::App& app, CliContext& ctx) {
  auto o = std::make_shared<FetchOptions>();
  auto* cmd = app.add_subcommand("fetch", "download a succeeded job's artifacts");
  cmd->add_option("JOB", o->job, "job id, unique id prefix, or jobs/{id}")->required();
  cmd->add_option("--out", o->out, "destination folder")->required();
  cmd->add_option("--only", o->only,
                  "only these artifacts: file names (mesh.vtu) or kinds (vtu, msh, medit, "
                  "labels, images, segmentation, report, curve, metrics)");
  cmd->add_option("--reduction", o->reduction,
                  "the mesh at this reduction (0..0.99] from the job's level record (a job "
                  "submitted with --outputs ...,levels), without simplifying again: a level job "
                  "is queued and its artifacts fetched; --only mesh kinds choose its outputs "
                  "(default vtu)")
      ->check(CLI::Range(0.0, 0.99));
  AddOutputFlags(cmd, ctx.flags);
  return {cmd, [&ctx, o] { return RunFetch(ctx, *o); }};
}

}  // namespace decima::client
