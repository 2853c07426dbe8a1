// decima-bench: reproducible figures for the pipeline stages.
//
//   decima-bench --input PATH|phantom:NxNxN --stages load,tetra --repeat 3 --json
//
// Every stage runs --repeat times on the output of the previous stage; `seconds` is the median
// and `seconds_all` every run. The process's peak resident memory after the stage is reported
// as `peak_rss_mb` (peak over the process so far, so it grows monotonically across stages).
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <functional>
#include <iostream>
#include <optional>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

#include <CLI/CLI.hpp>
#include <nlohmann/json.hpp>

#include "absl/strings/numbers.h"
#include "absl/strings/str_split.h"
#include "core/io/volume_io.h"
#include "core/mesh/tetrahedralize.h"
#include "core/volume/phantom.h"

namespace decima {
namespace {

using Json = nlohmann::ordered_json;

double PeakRssMb() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return usage.ru_maxrss / 1024.0;  // Linux reports kilobytes
}

double LoadAverage() {
  double load[1] = {0};
  return getloadavg(load, 1) == 1 ? load[0] : -1.0;
}

// Runs `fn` `repeat` times and fills seconds (median) and seconds_all.
absl::Status Time(int repeat, Json& out, const std::function<absl::Status()>& fn) {
  std::vector<double> runs;
  for (int r = 0; r < repeat; ++r) {
    const auto start = std::chrono::steady_clock::now();
    absl::Status s = fn();
    if (!s.ok()) return s;
    runs.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count());
  }
  out["seconds_all"] = runs;
  std::sort(runs.begin(), runs.end());
  out["seconds"] = runs[runs.size() / 2];
  out["peak_rss_mb"] = PeakRssMb();
  return absl::OkStatus();
}

// "phantom:NxNxN" or "phantom:N" -> dims; nullopt if `input` is not a phantom spec.
absl::StatusOr<std::optional<std::array<int64_t, 3>>> ParsePhantom(const std::string& input) {
  if (input.rfind("phantom:", 0) != 0) return std::nullopt;
  std::vector<std::string> parts = absl::StrSplit(input.substr(8), 'x');
  std::array<int64_t, 3> dims{};
  if (parts.size() == 1) parts = {parts[0], parts[0], parts[0]};
  if (parts.size() != 3) {
    return absl::InvalidArgumentError("--input: expected phantom:NxNxN, got '" + input + "'");
  }
  for (int c = 0; c < 3; ++c) {
    if (!absl::SimpleAtoi(parts[c], &dims[c]) || dims[c] < 2) {
      return absl::InvalidArgumentError("--input: phantom size '" + parts[c] +
                                        "' is not an integer >= 2");
    }
  }
  return std::optional<std::array<int64_t, 3>>(dims);
}

void DescribeVolume(const Volume& v, Json& out) {
  out["dims"] = v.dims;
  out["voxels"] = v.voxel_count();
  out["type"] = std::string(VoxelTypeName(v.type));
}

struct BenchState {
  Volume image;
  std::optional<Volume> labels;
  std::optional<TetMesh> mesh;
};

absl::Status RunLoad(const std::string& input, int repeat, BenchState& state, Json& out) {
  auto phantom_dims = ParsePhantom(input);
  if (!phantom_dims.ok()) return phantom_dims.status();
  if (!phantom_dims->has_value()) {
    absl::Status s = Time(repeat, out, [&]() -> absl::Status {
      auto v = io::ReadVolume(input);
      if (!v.ok()) return v.status();
      state.image = *std::move(v);
      return absl::OkStatus();
    });
    if (!s.ok()) return s;
    DescribeVolume(state.image, out);
    return absl::OkStatus();
  }
  HeadPhantomOptions o;
  o.dims = **phantom_dims;
  o.region_means = {0, 1000, 400};
  o.noise_sigma = 50;
  absl::Status s = Time(repeat, out, [&]() -> absl::Status {
    auto p = MakeHeadPhantom(o);
    if (!p.ok()) return p.status();
    state.image = std::move(p->image);
    state.labels = std::move(p->labels);
    return absl::OkStatus();
  });
  if (!s.ok()) return s;
  DescribeVolume(state.image, out);
  return absl::OkStatus();
}

absl::Status RunTetra(int repeat, BenchState& state, Json& out) {
  TetrahedralizeOptions opts;
  opts.labels = state.labels ? &*state.labels : nullptr;
  absl::Status s = Time(repeat, out, [&]() -> absl::Status {
    state.mesh.reset();  // measure one mesh alive at a time, as the pipeline holds it
    auto m = Tetrahedralize(state.image, opts);
    if (!m.ok()) return m.status();
    state.mesh = *std::move(m);
    return absl::OkStatus();
  });
  if (!s.ok()) return s;
  out["vertices"] = state.mesh->vertex_count();
  out["tets"] = state.mesh->tet_count();
  return absl::OkStatus();
}

int Main(int argc, char** argv) {
  CLI::App app{"decima-bench: time Decima's pipeline stages on one input and print JSON"};
  std::string input, stages_arg = "load,tetra";
  int repeat = 3;
  bool json = false;
  app.add_option("--input", input, "Volume file, DICOM folder, or phantom:NxNxN (synthetic head)")
      ->required();
  app.add_option("--stages", stages_arg, "Comma-separated stages, in pipeline order: load,tetra")
      ->capture_default_str();
  app.add_option("--repeat", repeat, "Runs per stage; the median is reported")
      ->check(CLI::Range(1, 100))
      ->capture_default_str();
  app.add_flag("--json", json, "Print the JSON object (the only output format; kept for scripts)");
  CLI11_PARSE(app, argc, argv);

  const std::vector<std::string> known = {"load", "tetra"};
  std::vector<std::string> stages = absl::StrSplit(stages_arg, ',', absl::SkipEmpty());
  for (const auto& s : stages) {
    if (std::find(known.begin(), known.end(), s) == known.end()) {
      std::cerr << "decima-bench: unknown stage '" << s << "' (known: load, tetra)\n";
      return 2;
    }
  }
  if (stages.empty() || stages[0] != "load") stages.insert(stages.begin(), "load");

  Json result;
  result["input"] = input;
  result["repeat"] = repeat;
  result["machine"] = {{"cores", std::thread::hardware_concurrency()},
                       {"load_average_1m", LoadAverage()}};
  BenchState state;
  for (const auto& stage : stages) {
    Json out;
    absl::Status s;
    if (stage == "load")
      s = RunLoad(input, repeat, state, out);
    else if (stage == "tetra")
      s = RunTetra(repeat, state, out);
    if (!s.ok()) {
      std::cerr << "decima-bench: stage " << stage << ": " << s << "\n";
      return 1;
    }
    result["stages"][stage] = out;
  }
  result["peak_rss_mb"] = PeakRssMb();
  std::cout << result.dump(2) << std::endl;
  return 0;
}

}  // namespace
}  // namespace decima

int main(int argc, char** argv) { return decima::Main(argc, argv); }
