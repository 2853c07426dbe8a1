#include "client/cli/volume_upload.h"

#include <cstdio>

#include "core/io/volume_io.h"
#include "decima/v1/jobs.grpc.pb.h"

namespace decima::client {

namespace fs = std::filesystem;

int CheckJobMemoryBeforeUpload(CliContext& ctx, const fs::path& input, const v1::JobSpec& spec) {
  std::error_code ec;
  if (fs::is_directory(input, ec)) return kOk;  // DICOM: dims only after reading the series
  auto header = io::ProbeVolume(input);
  if (!header.ok() || !header->parsed) return kOk;  // CreateVolume names what is wrong
  v1::CheckJobMemoryRequest req;
  *req.mutable_spec() = spec;
  req.set_display_name(input.filename().string());
  for (int64_t d : header->dims) req.add_dims(d);
  req.set_size_bytes(static_cast<int64_t>(fs::file_size(input, ec)));
  if (ec) req.set_size_bytes(0);
  auto jobs = v1::Jobs::NewStub(ctx.conn.channel);
  v1::CheckJobMemoryResponse resp;  // fits, the estimate and the limit: nothing to show
  grpc::Status s = WithRetry(ctx, [&] {
    auto call = ctx.conn.Context();
    return jobs->CheckJobMemory(call.get(), req, &resp);
  });
  if (s.error_code() == grpc::StatusCode::UNIMPLEMENTED) return kOk;  // an older server
  if (!s.ok()) return Report(ctx, s, "submit");
  return kOk;
}

int MakeVolume(CliContext& ctx, const fs::path& input, const std::string& series,
               const std::string& request_id, std::string* name) {
  std::vector<InputFile> files;
  std::string err;
  if (!CollectInputs(input, &files, &err) || !AddHeaderDataFiles(&files, &err)) {
    return InputError(ctx, err);
  }
  std::error_code ec;
  if (fs::is_directory(input, ec)) {
    const std::vector<std::string> dropped = KeepDicomFiles(&files);
    if (!dropped.empty() && !ctx.flags.quiet) {
      std::string list;
      for (size_t i = 0; i < dropped.size() && i < 5; ++i) list += " " + dropped[i];
      std::fprintf(stderr,
                   "decima: warning: skipping %zu file(s) of %s that are not DICOM images:%s%s\n",
                   dropped.size(), input.c_str(), list.c_str(), dropped.size() > 5 ? " ..." : "");
    }
    if (files.empty()) {
      return InputError(ctx, input.string() +
                                 ": no DICOM file in the folder (none has the DICM marker); give a "
                                 "volume file or a folder of DICOM images");
    }
  }
  return UploadVolume(ctx, input, std::move(files), input.filename().string(), series, request_id,
                      name);
}
int UploadVolume(CliContext& ctx, const fs::path& input, std::vector<InputFile> files,
                 const std::string& display_name, const std::string& series,
                 const std::string& request_id, std::string* name) {
  std::string err;
  if (!HashInputs(&files, &err)) return InputError(ctx, err);
  int64_t total = 0, sent = 0, present = 0;
  for (const auto& f : files) total += f.size;
  v1::CreateVolumeRequest req;
  std::string manifest;
  for (const auto& f : files) {
    int64_t resumed = 0;
    // One bar for the whole volume: the bytes of all its files.
    grpc::Status s = WithRetry(ctx, [&] {
      return UploadBlob(
          ctx.conn, f,
          [&](int64_t d, int64_t) {
            if (d < f.size || resumed < f.size)
              ByteBar(ctx, "upload " + input.filename().string(), sent + d, total);
          },
          4, &resumed);
    });
    if (!s.ok()) return Report(ctx, s, "upload " + f.path.string());
    if (resumed == f.size) present += f.size;
    if (resumed > 0 && resumed < f.size && !ctx.Quiet()) {
      std::fprintf(stderr, "\ndecima: resumed upload of %s at byte %lld of %lld\n", f.name.c_str(),
                   static_cast<long long>(resumed), static_cast<long long>(f.size));
    }
    sent += f.size;
    auto* vf = req.mutable_volume()->add_files();
    vf->set_path(f.name);
    vf->set_blob("blobs/" + f.sha256);
    manifest += f.name + "\n" + f.sha256 + "\n";
  }
  if (!ctx.Quiet() && present != total && ctx.stderr_tty) std::fprintf(stderr, "\r\033[K");
  req.mutable_volume()->set_display_name(display_name);
  req.mutable_volume()->set_series_instance_uid(series);
  req.set_request_id(
      request_id.empty()
          ? NewRequestId()
          : "vol-" + Sha256HexOf(request_id + "\n" + series + "\n" + manifest).substr(0, 32));
  auto stub = v1::Volumes::NewStub(ctx.conn.channel);
  v1::Volume vol;
  grpc::Status s =
      WithRetry(ctx, [&] { return stub->CreateVolume(ctx.conn.Context().get(), req, &vol); });
  if (!s.ok()) return Report(ctx, s, "create volume from " + input.string());
  if (!ctx.Quiet()) {
    // Said after CreateVolume: only the server knows whether these files are a volume already.
    if (vol.reused()) {
      std::fprintf(stderr, "decima: reusing %s: the same %zu file(s) as %s (%s)\n",
                   vol.name().c_str(), files.size(), input.c_str(), FormatBytes(total).c_str());
    } else if (present == total) {
      std::fprintf(stderr, "decima: %s already on the server (%zu file(s), %s)\n", input.c_str(),
                   files.size(), FormatBytes(total).c_str());
    } else if (!ctx.stderr_tty) {
      std::fprintf(stderr, "decima: uploaded %s (%zu file(s), %s)\n", input.c_str(), files.size(),
                   FormatBytes(total - present).c_str());
    }
    std::fprintf(stderr, "decima: %s = %s %s", vol.name().c_str(),
                 TerminalSafe(vol.display_name()).c_str(),
                 v1::VolumeFormat_Name(vol.format()).c_str());
    if (vol.dims_size() == 3) {
      std::fprintf(stderr, " %lldx%lldx%lld voxels, %.3gx%.3gx%.3g mm",
                   static_cast<long long>(vol.dims(0)), static_cast<long long>(vol.dims(1)),
                   static_cast<long long>(vol.dims(2)), vol.spacing(0), vol.spacing(1),
                   vol.spacing(2));
    }
    if (!vol.modality().empty()) std::fprintf(stderr, " %s", vol.modality().c_str());
    std::fprintf(stderr, ", %s\n", FormatBytes(vol.size_bytes()).c_str());
  }
  ctx.volumes[vol.name()] = vol;
  *name = vol.name();
  return kOk;
}

}  // namespace decima::client
