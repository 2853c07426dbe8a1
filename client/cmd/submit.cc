// decima submit INPUT [job options] [--watch] [--out DIR]: uploads a volume (a file, a header
// with its data files, a DICOM folder, or a series pulled by --dicomweb) and queues a job;
// several INPUTs or --each FOLDER: a batch, one job per study found (client/batch.h).
#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <optional>

#include "client/batch.h"
#include "client/cli/dicomweb_flags.h"
#include "client/cli/output.h"
#include "client/cli/volume_upload.h"
#include "client/cli/watch.h"
#include "client/cmd/commands.h"
#include "client/text.h"

namespace decima::client {

namespace fs = std::filesystem;

namespace {

struct SubmitOptions {
  std::vector<std::string> inputs;
  fs::path each;
  DicomWebFlags dicomweb;
  std::string label_map, policy = "field", interfaces, mesh_compression, transfer_function, fault,
                         request_id, series;
  fs::path out;
  // Unset options stay unset in the request: the server owns the defaults.
  std::optional<int> regions, image_size, vtu_level, stream_slab_voxels;
  std::optional<double> reduction, tolerance, min_psnr;
  std::vector<double> class_means;
  std::vector<std::string> weights, views, view_list, outputs, only, region_names;
  std::string region_names_flag;  // split by CheckRegionNames, keeping empty names to refuse
  bool watch = false;
};

// --region-names, checked before anything is uploaded with the server's rule
// (core/volume/regions.h ValidateRegionNames; the client does not link core, so it is restated
// here and CreateJob checks again). Without --regions the names set K.
int CheckRegionNames(SubmitOptions& o) {
  // Split here, not by CLI11's delimiter, which drops empty items: "air,,bone" must be refused,
  // not become two names.
  o.region_names.clear();
  if (o.region_names_flag.empty()) return kOk;
  for (size_t at = 0;;) {
    const size_t comma = o.region_names_flag.find(',', at);
    o.region_names.push_back(o.region_names_flag.substr(at, comma - at));
    if (comma == std::string::npos) break;
    at = comma + 1;
  }
  if (o.regions && static_cast<size_t>(*o.regions) != o.region_names.size()) {
    std::fprintf(stderr, "decima: --region-names: %zu names for --regions %d\n",
                 o.region_names.size(), *o.regions);
    return kUsage;
  }
  for (size_t i = 0; i < o.region_names.size(); ++i) {
    const std::string& n = o.region_names[i];
    const char* problem = nullptr;
    if (n.find_first_not_of(' ') == std::string::npos) problem = "is empty";
    if (n.size() > 64) problem = "is longer than 64 bytes";
    for (size_t j = 0; j < n.size() && problem == nullptr; ++j) {
      const auto c = static_cast<unsigned char>(n[j]);
      if (c < 0x20 || c == 0x7f) problem = "holds a control character";
      if (c == '\\') problem = "holds a backslash";
    }
    for (size_t k = 0; k < i && problem == nullptr; ++k) {
      if (AsciiLower(n) == AsciiLower(o.region_names[k])) problem = "appears twice";
    }
    if (problem != nullptr) {
      std::fprintf(stderr, "decima: --region-names: name %zu %s\n", i + 1, problem);
      return kUsage;
    }
  }
  return kOk;
}

// --views and the repeated --view, in order. "--views 30,20" splits into "30" and "20", never
// views on their own: such pairs are joined.
std::vector<std::string> AllViews(const SubmitOptions& o) {
  auto number = [](const std::string& s) {
    char* end = nullptr;
    std::strtod(s.c_str(), &end);
    return !s.empty() && end == s.c_str() + s.size();
  };
  std::vector<std::string> all;
  for (size_t i = 0; i < o.view_list.size(); ++i) {
    if (number(o.view_list[i]) && i + 1 < o.view_list.size() && number(o.view_list[i + 1])) {
      all.push_back(o.view_list[i] + ":" + o.view_list[i + 1]);
      ++i;
    } else {
      all.push_back(o.view_list[i]);
    }
  }
  all.insert(all.end(), o.views.begin(), o.views.end());
  return all;
}

// --weight NAME=VALUE overrides.
int SetWeights(const std::vector<std::string>& weights, v1::ErrorWeights* ew) {
  for (const auto& w : weights) {
    auto eq = w.find('=');
    if (eq == std::string::npos) {
      std::fprintf(stderr, "decima: --weight %s: expected NAME=VALUE\n", w.c_str());
      return kUsage;
    }
    const std::string name = AsciiLower(w.substr(0, eq));
    double value = 0;
    try {
      value = std::stod(w.substr(eq + 1));
    } catch (...) {
      std::fprintf(stderr, "decima: --weight %s: VALUE is not a number\n", w.c_str());
      return kUsage;
    }
    if (name == "w_r" || name == "regional") {
      ew->set_regional(value);
    } else if (name == "w_g" || name == "gradient") {
      ew->set_gradient(value);
    } else if (name == "w_s" || name == "shape") {
      ew->set_shape(value);
    } else if (name == "w_v" || name == "volume") {
      ew->set_volume(value);
    } else if (name == "w_n" || name == "neighbour") {
      ew->set_neighbour(value);
    } else {
      std::fprintf(stderr, "decima: --weight %s: unknown weight (w_r, w_g, w_s, w_v, w_n)\n",
                   w.c_str());
      return kUsage;
    }
  }
  return kOk;
}

// Everything of the spec but its volume, from the flags (the same for every study of a batch).
int FillSpec(const SubmitOptions& o, v1::JobSpec* spec) {
  if (o.regions) spec->set_regions(*o.regions);
  if (!o.regions && !o.region_names.empty()) {
    spec->set_regions(static_cast<int>(o.region_names.size()));
  }
  for (const auto& n : o.region_names) spec->add_region_names(n);
  for (double m : o.class_means) spec->add_class_means(m);
  if (o.reduction) spec->set_target_reduction(*o.reduction);
  spec->set_policy(o.policy == "paper"       ? v1::PAPER
                   : o.policy == "tetfusion" ? v1::TETFUSION
                                             : v1::FIELD);
  if (o.tolerance) spec->set_error_tolerance(*o.tolerance);
  if (o.min_psnr) spec->set_min_psnr(*o.min_psnr);
  if (o.stream_slab_voxels) spec->set_stream_slab_voxels(*o.stream_slab_voxels);
  if (!o.interfaces.empty()) spec->set_interfaces(o.interfaces);
  if (!o.weights.empty()) {
    if (int rc = SetWeights(o.weights, spec->mutable_weights()); rc != kOk) return rc;
  }
  for (const auto& v : AllViews(o)) spec->add_views(v);
  if (o.image_size) spec->set_image_size(*o.image_size);
  spec->set_transfer_function(o.transfer_function);
  for (const auto& out : o.outputs) spec->add_outputs(out);
  if (o.vtu_level) spec->set_vtu_compression_level(*o.vtu_level);
  if (!o.mesh_compression.empty()) spec->set_mesh_compression(o.mesh_compression);
  return kOk;
}

// CreateJob, retried while the server restarts; --fault goes along as metadata (read only by a
// server run with --allow-faults, server/jobs/faults.h).
grpc::Status CreateJob(CliContext& ctx, const SubmitOptions& o, const v1::CreateJobRequest& req,
                       v1::Job* job) {
  auto jobs = v1::Jobs::NewStub(ctx.conn.channel);
  return WithRetry(ctx, [&] {
    auto call = ctx.conn.Context();
    if (!o.fault.empty()) call->AddMetadata("decima-test-fault", o.fault);
    return jobs->CreateJob(call.get(), req, job);
  });
}

// Volumes made for a job the server refused (best effort: the refusal is what gets reported).
// Only those this run's CreateVolume made: a reused volume is the caller's from before.
void DeleteVolumes(CliContext& ctx, const std::vector<std::string>& names) {
  auto vstub = v1::Volumes::NewStub(ctx.conn.channel);
  for (const std::string& name : names) {
    auto made = ctx.volumes.find(name);
    if (name.empty() || made == ctx.volumes.end() || made->second.reused()) continue;
    v1::DeleteVolumeRequest dreq;
    dreq.set_name(name);
    v1::DeleteVolumeResponse dresp;
    (void)vstub->DeleteVolume(ctx.conn.Context().get(), dreq, &dresp);
  }
}

int SubmitOne(CliContext& ctx, const SubmitOptions& o, const std::string& input) {
  v1::CreateJobRequest req;
  auto* spec = req.mutable_spec();
  if (int frc = FillSpec(o, spec); frc != kOk) return frc;
  // A job that cannot fit is refused before its volume is uploaded.
  if (int mrc = CheckJobMemoryBeforeUpload(ctx, input, *spec); mrc != kOk) return mrc;
  int rc = MakeVolume(ctx, input, o.series, o.request_id, spec->mutable_volume());
  if (rc != kOk) return rc;
  if (!o.label_map.empty()) {
    rc = MakeVolume(ctx, o.label_map, "", o.request_id.empty() ? "" : o.request_id + "/label-map",
                    spec->mutable_label_map());
    if (rc != kOk) return rc;
  }
  req.set_request_id(o.request_id.empty() ? NewRequestId() : o.request_id);
  v1::Job job;
  grpc::Status s = CreateJob(ctx, o, req, &job);
  if (!s.ok()) {
    // Volumes made for this job only (a fresh request id) are not left behind by a refused
    // job; with --request-id they may belong to the job made first, so they stay.
    if (o.request_id.empty()) DeleteVolumes(ctx, {spec->volume(), spec->label_map()});
    return Report(ctx, s, "submit");
  }
  if (ctx.JsonOut()) {
    std::printf("%s\n", ToJson(job).c_str());
  } else {
    std::printf("%s\n", job.name().c_str());
  }
  std::fflush(stdout);
  if (!o.watch && o.out.empty()) return kOk;
  v1::Job final;
  rc = Watch(ctx, job.name(), &final);
  if ((rc != kOk && rc != kTargetNotReached) || o.out.empty()) return rc;
  const int frc = FetchArtifacts(ctx, final, o.out, o.only);
  return frc != kOk ? frc : rc;
}

// The jobs a batch made, in table order.
struct BatchJobs {
  std::vector<StudyRow> rows;
  std::vector<std::string> names;   // the jobs made
  std::vector<size_t> job_rows;     // their rows
  std::vector<std::string> labels;  // their studies' labels, for --out folders
};

// Uploads one study and queues its job: a row either way. Returns kOk, or the study's error
// (kUnavailable and kUnauthenticated stop the batch).
int QueueStudy(CliContext& ctx, const SubmitOptions& o, const v1::JobSpec& common,
               const Study& study, BatchJobs* b) {
  // A batch's request id gives each study its own, stable across retries of the batch.
  const std::string rid =
      o.request_id.empty() ? "" : o.request_id + "/" + Sha256HexOf(study.label).substr(0, 16);
  ctx.last_error.clear();
  v1::CreateJobRequest jreq;
  *jreq.mutable_spec() = common;
  int vrc = study.dicom() ? kOk : CheckJobMemoryBeforeUpload(ctx, study.input, common);
  if (vrc == kOk) {
    vrc = study.dicom()
              ? UploadVolume(ctx, study.input, study.files, study.display_name, study.series_uid,
                             rid, jreq.mutable_spec()->mutable_volume())
              : MakeVolume(ctx, study.input, "", rid, jreq.mutable_spec()->mutable_volume());
  }
  if (vrc == kOk) {
    jreq.set_request_id(rid.empty() ? NewRequestId() : rid);
    v1::Job job;
    grpc::Status s = CreateJob(ctx, o, jreq, &job);
    if (s.ok()) {
      b->rows.push_back({job.name(), study.label, v1::JobState_Name(job.state()), "", kOk});
      b->names.push_back(job.name());
      b->job_rows.push_back(b->rows.size() - 1);
      b->labels.push_back(study.label);
      return kOk;
    }
    vrc = Report(ctx, s, "submit " + study.label);
    // As for one INPUT: no volume left behind by a refusal.
    if (o.request_id.empty()) DeleteVolumes(ctx, {jreq.spec().volume()});
  }
  b->rows.push_back({"-", study.label, "REFUSED", ctx.last_error, kJobFailed});
  return vrc;
}

// Every study of every source, queued one after the other; kOk, or the error that stopped it.
int QueueBatch(CliContext& ctx, const SubmitOptions& o, const v1::JobSpec& common,
               const std::vector<fs::path>& sources, BatchJobs* b) {
  int number = 0;
  std::string err;
  for (const auto& source : sources) {
    std::vector<Study> studies;
    if (!FindStudies(source, &studies, &err) || studies.empty()) {
      const std::string why = err.empty()
                                  ? "no volume in it (no DICOM file, no .nii, .nii.gz, .mha, .mhd, "
                                    ".nrrd or .nhdr)"
                                  : err;
      std::fprintf(stderr, "decima: skipped %s: %s\n", source.c_str(), why.c_str());
      b->rows.push_back({"-", source.string(), "SKIPPED", why, kOk});
      err.clear();
      continue;
    }
    for (const Study& study : studies) {
      if (!ctx.Quiet())
        std::fprintf(stderr, "decima: study %d: %s\n", ++number, study.label.c_str());
      const int rc = QueueStudy(ctx, o, common, study, b);
      if (rc == kUnavailable || rc == kUnauthenticated) return rc;
    }
  }
  return kOk;
}

int SubmitBatch(CliContext& ctx, const SubmitOptions& o) {
  // One label map is on one volume's grid, one series UID picks within one folder: neither
  // means anything for several studies.
  if (!o.label_map.empty() || !o.series.empty()) {
    std::fprintf(stderr, "decima: submit: --label-map and --series take one INPUT, not a batch\n");
    return kUsage;
  }
  v1::JobSpec common;
  if (int frc = FillSpec(o, &common); frc != kOk) return frc;
  std::vector<fs::path> sources;
  std::string err;
  if (!o.each.empty() && !EachEntry(o.each, &sources, &err)) {
    std::fprintf(stderr, "decima: %s\n", err.c_str());
    return kUsage;
  }
  for (const auto& i : o.inputs) sources.emplace_back(i);
  BatchJobs b;
  // The server went away or refused the caller: stop, and show the table so far.
  if (int fatal = QueueBatch(ctx, o, common, sources, &b); fatal != kOk) {
    PrintStudyTable(ctx, b.rows);
    std::fprintf(stderr, "decima: submit: stopped the batch after %zu stud%s: %s\n", b.rows.size(),
                 b.rows.size() == 1 ? "y" : "ies", ctx.last_error.c_str());
    return fatal;
  }
  if (b.names.empty() && std::none_of(b.rows.begin(), b.rows.end(),
                                      [](const StudyRow& r) { return r.state == "REFUSED"; })) {
    std::fprintf(stderr, "decima: submit: no volume found in any INPUT or --each entry\n");
    return kUsage;
  }
  if ((o.watch || !o.out.empty()) && !b.names.empty()) {
    const std::vector<WatchOutcome> outcomes = WatchMany(ctx, b.names);
    std::vector<std::string> taken;
    for (size_t k = 0; k < b.names.size(); ++k) {
      StudyRow& row = b.rows[b.job_rows[k]];
      SetOutcome(outcomes[k], &row);
      if (o.out.empty() || outcomes[k].final.state() != v1::SUCCEEDED) continue;
      // Each study's artifacts in a folder of its own, named after the study.
      const int frc = FetchArtifacts(ctx, outcomes[k].final,
                                     o.out / ArtifactFolderName(b.labels[k], &taken), o.only);
      if (frc != kOk) {
        row.rc = frc;
        row.detail += "; fetch failed";
      }
    }
  }
  PrintStudyTable(ctx, b.rows);
  PrintStudyCounts(ctx, b.rows);
  std::vector<int> codes;
  for (const auto& r : b.rows) {
    if (r.state != "SKIPPED") codes.push_back(r.rc);
  }
  return BatchExitCode(codes);
}

// Removes the folder a --dicomweb submit pulled into, once the upload is done (or failed).
struct RemovePulled {
  fs::path dir;
  ~RemovePulled() {
    std::error_code ec;
    if (!dir.empty()) fs::remove_all(dir, ec);
  }
};

int RunSubmit(CliContext& ctx, SubmitOptions& o) {
  if (int rc = CheckRegionNames(o); rc != kOk) return rc;
  // Refused before anything is uploaded; the server refuses it too (spec.min_psnr), for clients
  // that skip this check.
  if (o.min_psnr && !(std::isfinite(*o.min_psnr) && *o.min_psnr > 0)) {
    std::fprintf(stderr,
                 "decima: submit: --min-psnr %g: expected a PSNR floor in dB, finite and > 0\n",
                 *o.min_psnr);
    return kUsage;
  }
  if (o.stream_slab_voxels && *o.stream_slab_voxels != 0 && *o.stream_slab_voxels < 4) {
    std::fprintf(stderr,
                 "decima: submit: --stream-slab-voxels %d: expected 0 (in memory) or at least 4 "
                 "voxel layers per slab\n",
                 *o.stream_slab_voxels);
    return kUsage;
  }
  if (o.min_psnr && o.policy != "field") {
    std::fprintf(stderr,
                 "decima: submit: --min-psnr needs --policy field (its recorded levels are "
                 "searched for the floor), not %s\n",
                 o.policy.c_str());
    return kUsage;
  }
  std::string input;
  RemovePulled pulled;
  // DICOMweb: pull into a folder first, then upload it like any DICOM folder.
  if (!o.dicomweb.web.base_url.empty()) {
    if (!o.inputs.empty() || !o.each.empty()) {
      std::fprintf(stderr, "decima: submit: give INPUT (or --each) or --dicomweb, not both\n");
      return kUsage;
    }
    if (int rc = ReadDicomWebToken(o.dicomweb); rc != kOk) return rc;
    o.dicomweb.web.series_uid = o.series;
    char tmpl[] = "/tmp/decima-dicomweb-XXXXXX";
    if (::mkdtemp(tmpl) == nullptr) {
      std::fprintf(stderr, "decima: cannot create a temporary folder\n");
      return kError;
    }
    const fs::path dir = tmpl;
    if (int rc = PullDicomWebInto(ctx, o.dicomweb, dir, false, dir); rc != kOk) return rc;
    pulled.dir = dir;
    input = dir.string();
  }
  // Several inputs, or --each: a batch, one job per study (client/batch.h).
  const bool batch = o.inputs.size() > 1 || !o.each.empty();
  if (o.inputs.size() == 1 && !batch) input = o.inputs[0];
  if (input.empty() && !batch) {
    std::fprintf(stderr, "decima: submit: INPUT or --dicomweb URL --study UID is required\n");
    return kUsage;
  }
  if (int rc = ConnectAndCheck(ctx, "submit"); rc != kOk) return rc;
  return batch ? SubmitBatch(ctx, o) : SubmitOne(ctx, o, input);
}

void AddJobFlags(CLI::App* cmd, SubmitOptions& o) {
  cmd->add_option("--regions,-k", o.regions, "K regions of the segmentation (2..8, default 3)");
  cmd->add_option("--class-means", o.class_means, "K class means instead of k-means")
      ->delimiter(',');
  cmd->add_option("--region-names", o.region_names_flag,
                  "names of the regions in label order, comma-separated, e.g. air,brain,bone "
                  "(sets K when --regions is not given; each 1..64 bytes, unique; default: "
                  "air/soft tissue/bone by HU for CT, else region 1 (darkest) ...)");
  cmd->add_option("--label-map", o.label_map,
                  "a label map on the same grid (replaces the level set)");
  cmd->add_option("--reduction", o.reduction,
                  "target_reduction: fraction of cells to remove (0..0.99, default 0.5; 0 = "
                  "no target, stop on --tolerance)");
  cmd->add_option("--policy", o.policy, "simplification policy: paper, tetfusion or field")
      ->transform(CLI::IsMember({"paper", "tetfusion", "field"}, CLI::ignore_case))
      ->capture_default_str();
  cmd->add_option("--tolerance", o.tolerance, "error tolerance (>= 0; default 0 = none)");
  cmd->add_option("--interfaces", o.interfaces,
                  "field policy: free (default: interfaces move wherever every voxel centre "
                  "keeps its label) or voxel-faces (the voxel staircase kept as a set)")
      ->check(CLI::IsMember({"free", "voxel-faces"}));
  cmd->add_option("--min-psnr", o.min_psnr,
                  "PSNR floor in dB (field policy): simplify as far as possible while the "
                  "field's PSNR against the original grid stays >= DB; --reduction is then the "
                  "maximum (default with a floor: none), whichever stops first wins")
      ->type_name("DB");
  cmd->add_option("--stream-slab-voxels", o.stream_slab_voxels,
                  "simplify in slabs of N voxel layers along z (>= 4; field policy with a "
                  "--reduction, no --min-psnr, levels or curve output): about half the memory "
                  "for a PSNR 0.2-1.7 % lower; 0 = in memory (default: the server streams, in "
                  "slabs of 16, only a job that does not fit its memory limit in memory)")
      ->type_name("N");
  cmd->add_option("--weight", o.weights,
                  "weight override NAME=VALUE (w_r/regional, w_g/gradient, w_s/shape, "
                  "w_v/volume, w_n/neighbour)");
  cmd->add_option("--views", o.view_list,
                  "render views, comma-separated: anterior, posterior, left, lateral, right, "
                  "superior, inferior, oblique or AZIMUTH:ELEVATION (default anterior)")
      ->delimiter(',');
  cmd->add_option("--view", o.views, "one render view (repeatable), e.g. --view 30:20");
  cmd->add_option("--image-size", o.image_size, "rendered image size, pixels (default 512)");
  cmd->add_option("--transfer-function", o.transfer_function, "preset name, auto, or JSON");
  cmd->add_option("--outputs", o.outputs,
                  "artifacts to produce, comma-separated: vtu, msh, medit, stl, glb, levels, "
                  "labels, images, segmentation, report, curve (default "
                  "vtu,labels,images,segmentation,report; metrics.json always; stl = one "
                  "closed surface per region, surface-<name>.stl; glb = all of them, named "
                  "and coloured, in surfaces.glb; levels = mesh.levels, the collapse record "
                  "down to 90 %, from which any level of detail can be extracted later (field "
                  "policy; the run goes down to 90 %); curve = diff1 against cells removed, one "
                  "more simplification per 10 % step)")
      ->delimiter(',')
      ->transform(CLI::IsMember({"vtu", "msh", "medit", "stl", "glb", "levels", "labels", "images",
                                 "segmentation", "report", "curve"},
                                CLI::ignore_case));
  cmd->add_option("--mesh-compression", o.mesh_compression,
                  "mesh.vtu's compressor: zlib (default) or lzma (VTK's LZMA: ~44 % fewer bytes, "
                  "several times the write time, ~2x VTK's read time)")
      ->check(CLI::IsMember({"zlib", "lzma"}));
  cmd->add_option("--vtu-level", o.vtu_level,
                  "compression level of mesh.vtu (zlib's, or xz's preset with --mesh-compression "
                  "lzma): 0 uncompressed, 1 fastest (default) .. 9 smallest")
      ->check(CLI::Range(0, 9));
}

}  // namespace

Command NewCmdSubmit(CLI::App& app, CliContext& ctx) {
  auto o = std::make_shared<SubmitOptions>();
  auto* cmd = app.add_subcommand(
      "submit",
      "upload a volume (file or DICOM folder) and queue a job; several INPUTs or --each: one "
      "job per study found in them");
  cmd->add_option("INPUT", o->inputs,
                  "volume file (.nii, .nii.gz, .mha, .mhd + data, .nrrd, .nhdr + data) or "
                  "DICOM folder (or --dicomweb); several: a batch, one job per study found "
                  "in each (a volume file, or a DICOM series by SeriesInstanceUID)");
  cmd->add_option("--each", o->each,
                  "a batch of every entry of FOLDER (its subfolders and volume files), one "
                  "job per study found; a subfolder with no volume is reported and skipped");
  AddDicomWebFlags(cmd, o->dicomweb, /*is_pull=*/false);
  AddJobFlags(cmd, *o);
  cmd->add_option("--series", o->series,
                  "DICOM: the SeriesInstanceUID to use when the folder holds several series "
                  "(with --dicomweb: the series to pull)");
  cmd->add_option("--request-id", o->request_id,
                  "idempotency key (default: a new UUID); reused with other parameters it is "
                  "refused (ALREADY_EXISTS)");
  // Test seam (server/jobs/faults.h): sent as metadata, read only by a server run with
  // --allow-faults.
  cmd->add_option("--fault", o->fault, "test-only fault injection")->group("");
  cmd->add_flag("--watch", o->watch, "watch the job until it ends");
  cmd->add_option("--out", o->out,
                  "download the artifacts here when it succeeds (implies --watch)");
  cmd->add_option("--only", o->only, "with --out: download only these artifacts");
  AddOutputFlags(cmd, ctx.flags);
  return {cmd, [&ctx, o] { return RunSubmit(ctx, *o); }};
}

}  // namespace decima::client
