// TEMP dev pipeline (drop at merge): checks that the input exists, walks the documented stages
// with progress events and cancel checks, and writes small but valid placeholder artifacts so
// the service can be developed before the real pipeline lands.
#include <png.h>

#include <chrono>
#include <fstream>
#include <thread>

#include "absl/strings/str_cat.h"
#include "core/pipeline/pipeline.h"

namespace decima::pipeline {
namespace {

bool WritePng(const std::filesystem::path& path, int size, int seed) {
  png_image img{};
  img.version = PNG_IMAGE_VERSION;
  img.width = static_cast<png_uint_32>(size);
  img.height = static_cast<png_uint_32>(size);
  img.format = PNG_FORMAT_RGB;
  std::vector<unsigned char> px(static_cast<size_t>(size) * size * 3);
  for (size_t i = 0; i < px.size(); ++i) px[i] = static_cast<unsigned char>((i * 7 + seed) & 255);
  return png_image_write_to_file(&img, path.c_str(), 0, px.data(), 0, nullptr) != 0;
}

}  // namespace

absl::StatusOr<JobResult> RunJob(const JobSpec& spec, const std::filesystem::path& out_dir,
                                 const ProgressFn& progress, const CancelToken* cancel) {
  auto t0 = std::chrono::steady_clock::now();
  std::error_code ec;
  if (!std::filesystem::exists(spec.input, ec)) {
    return absl::InvalidArgumentError(absl::StrCat(spec.input.string(), ": no such file"));
  }
  std::filesystem::create_directories(out_dir, ec);
  for (const char* stage : {"load", "segment", "tetra", "simplify", "write", "render", "diff"}) {
    for (int i = 0; i <= 4; ++i) {
      if (auto s = CheckCancelled(cancel, stage); !s.ok()) return s;
      Report(progress, {stage, i / 4.0, "dev pipeline", {{"step", double(i)}}});
      std::this_thread::sleep_for(std::chrono::milliseconds(4));
    }
  }
  JobResult r;
  auto add = [&](const std::string& name) {
    std::filesystem::path p = out_dir / name;
    r.artifacts.push_back({name, p, std::filesystem::file_size(p, ec)});
  };
  std::ofstream(out_dir / "mesh.vtu")
      << "<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"0.1\">\n"
         "<UnstructuredGrid><Piece NumberOfPoints=\"4\" NumberOfCells=\"1\">\n"
         "<Points><DataArray type=\"Float32\" NumberOfComponents=\"3\" format=\"ascii\">"
         "0 0 0 1 0 0 0 1 0 0 0 1</DataArray></Points>\n"
         "<Cells><DataArray type=\"Int32\" Name=\"connectivity\" format=\"ascii\">0 1 2 3"
         "</DataArray><DataArray type=\"Int32\" Name=\"offsets\" format=\"ascii\">4</DataArray>"
         "<DataArray type=\"UInt8\" Name=\"types\" format=\"ascii\">10</DataArray></Cells>\n"
         "</Piece></UnstructuredGrid></VTKFile>\n";
  add("mesh.vtu");
  std::ofstream(out_dir / "mesh.msh") << "$MeshFormat\n4.1 0 8\n$EndMeshFormat\n";
  add("mesh.msh");
  int n = std::min(spec.image_size, 64);
  for (const char* png : {"original.png", "simplified.png", "diff.png", "comparison.png"}) {
    if (!WritePng(out_dir / png, n, png[0])) return absl::InternalError("png");
    add(png);
  }
  r.metrics_json = "{\"diff1\": 0.0, \"psnr_db\": 99.0, \"dice\": [1, 1, 1], \"dev\": true}";
  std::ofstream(out_dir / "metrics.json") << r.metrics_json;
  add("metrics.json");
  r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return r;
}

}  // namespace decima::pipeline
