#include "client/cli/describe.h"

#include <cstdio>

#include "client/cli/output.h"

namespace decima::client {

namespace {

// "phantom.nii (volumes/x, VOLUME_FORMAT_NIFTI, 12x10x8 voxels, 2x2x2 mm, CT, 2 KB)".
std::string DescribeVolume(const v1::Volume& vol) {
  std::string desc =
      vol.display_name() + " (" + vol.name() + ", " + v1::VolumeFormat_Name(vol.format());
  if (vol.dims_size() == 3) {
    char buf[128];
    std::snprintf(buf, sizeof buf, ", %lldx%lldx%lld voxels, %.3gx%.3gx%.3g mm",
                  static_cast<long long>(vol.dims(0)), static_cast<long long>(vol.dims(1)),
                  static_cast<long long>(vol.dims(2)), vol.spacing(0), vol.spacing(1),
                  vol.spacing(2));
    desc += buf;
  }
  if (!vol.modality().empty()) desc += ", " + vol.modality();
  return desc + ", " + FormatBytes(vol.size_bytes()) + ")";
}

}  // namespace

void DescribeJob(CliContext& ctx, const v1::Job& j) {
  auto line = [](const char* key, const std::string& value) {
    std::printf("%-14s %s\n", key, TerminalSafe(value).c_str());
  };
  line("Name:", j.name());
  line("State:", v1::JobState_Name(j.state()));
  if (j.state() == v1::RUNNING || j.state() == v1::QUEUED) {
    const v1::Progress& p = j.progress();
    line("Progress:",
         p.stage().empty()
             ? "-"
             : Percent(JobFraction(p, JobWithCurve(j))) + " overall, " + p.stage() + " " +
                   Percent(p.fraction()) + " " + p.message() +
                   (p.has_eta_seconds() ? ", ETA " + FormatDuration(p.eta_seconds()) : ""));
  }
  if (!j.error().message().empty()) line("Error:", j.error().message());
  const v1::Volume* vol = GetVolume(ctx, j.spec().volume());
  line("Input:", vol != nullptr ? DescribeVolume(*vol) : j.spec().volume());
  line("Request id:", j.request_id().empty() ? "-" : j.request_id());
  std::printf("Spec:\n");
  const v1::JobSpec& s = j.spec();
  std::printf("  regions %d, target_reduction %s, policy %s, error_tolerance %g\n", s.regions(),
              Percent(s.target_reduction(), 1).c_str(), v1::SimplifyPolicy_Name(s.policy()).c_str(),
              s.error_tolerance());
  std::string views, outputs;
  for (const auto& v : s.views()) views += (views.empty() ? "" : ", ") + v;
  for (const auto& o : s.outputs()) outputs += (outputs.empty() ? "" : ", ") + o;
  std::printf("  views %s, image_size %d, transfer_function %s\n", views.c_str(), s.image_size(),
              s.transfer_function().size() > 40 ? "(JSON)" : s.transfer_function().c_str());
  std::printf("  outputs %s, vtu_compression_level %d\n",
              outputs.empty() ? "(default)" : outputs.c_str(), s.vtu_compression_level());
  if (!s.label_map().empty()) std::printf("  label_map %s\n", s.label_map().c_str());
  if (!s.levels_of().empty()) {
    std::printf("  levels_of %s (the mesh is a level of that job's record)\n",
                s.levels_of().c_str());
  }
  if (s.has_min_psnr()) std::printf("  min_psnr %g dB\n", s.min_psnr());
  if (s.stream_slab_voxels() > 0) {
    std::printf("  simplified in slabs of %d voxel layers (stream_slab_voxels)\n",
                s.stream_slab_voxels());
  }
  if (!s.interfaces().empty()) std::printf("  interfaces %s\n", s.interfaces().c_str());
  if (!s.mesh_compression().empty()) {
    std::printf("  mesh_compression %s\n", s.mesh_compression().c_str());
  }
  std::printf("Times:\n");
  std::printf("  created %s, started %s, ended %s\n", FormatTime(j.create_time()).c_str(),
              FormatTime(j.start_time()).c_str(), FormatTime(j.end_time()).c_str());
  std::printf("  duration %s, attempts %d\n", FormatDuration(JobSeconds(j)).c_str(), j.attempts());
  if (j.state() == v1::SUCCEEDED) {
    std::printf("Result:\n");
    for (const auto& l : SummaryLines(SummarizeJob(j, vol != nullptr ? vol->size_bytes() : 0))) {
      std::printf("  %s\n", l.c_str());
    }
    for (const auto& l : FidelityLines(j.metrics_json())) std::printf("  %s\n", l.c_str());
    std::printf("Artifacts:\n");
    std::vector<std::vector<std::string>> rows = {{"  FILE", "SIZE", "SHA256"}};
    for (const auto& a : j.artifacts()) {
      rows.push_back({"  " + a.file_name(), FormatBytes(a.size_bytes()), a.sha256().substr(0, 12)});
    }
    PrintTable(rows);
  }
}

int PrintSummary(CliContext& ctx, const v1::Job& job) {
  const v1::Volume* vol = GetVolume(ctx, job.spec().volume());
  const JobSummary s = SummarizeJob(job, vol != nullptr ? vol->size_bytes() : 0);
  if (ctx.JsonOut()) {
    std::printf(
        "{\"summary\":{\"job\":%s,\"target_reduction\":%g,\"achieved_reduction\":%g,"
        "\"reached_target\":%s,\"cells_before\":%lld,\"cells_after\":%lld,"
        "\"artifact_bytes\":%lld,\"input_bytes\":%lld}}\n",
        JsonString(job.name()).c_str(), s.target_reduction, s.achieved_reduction,
        s.reached_target ? "true" : "false", static_cast<long long>(s.cells_before),
        static_cast<long long>(s.cells_after), static_cast<long long>(s.artifact_bytes),
        static_cast<long long>(s.input_bytes));
    std::fflush(stdout);
  }
  // The warning is printed even with -q: it changes the exit code.
  for (const auto& l : SummaryLines(s)) {
    if (!ctx.flags.quiet || l.rfind("WARNING", 0) == 0)
      std::fprintf(stderr, "decima: %s\n", l.c_str());
  }
  return s.Met() ? kOk : kTargetNotReached;
}

}  // namespace decima::client
