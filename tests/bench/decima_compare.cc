// decima-compare: Decima's simplification policies against VTK's quadric decimation on the same
// mesh, measured by the same code (core/metrics, core/render) in one run (issue 10, item 3).
//
//   decima-compare --input ct.nii.gz --reductions 0.5,0.8 --policies field,paper --repeat 3
//
// Steps: load the volume; labels from Segment (--regions) or, for phantom:N, the phantom's
// ground truth (as decima-bench does); Tetrahedralize; render the original once (its bounds
// give the camera of every render); write the original as .vtu into a scratch folder; then per
// target reduction:
//   - each Decima policy runs in a forked child (so one method's peak memory cannot hide in
//     another's): Simplify --repeat times (median seconds), the child's peak RSS right after,
//     then MeasureFidelity and the render diff of the last result;
//   - VTK: vtk_quadric_decimate.py (python3-vtk9) --repeat times as a child process; its time
//     around the filter's Update() and the subprocess wall time (medians), the child's max RSS
//     from wait4; its output is read back with ReadVtu and measured like Decima's.
// Output: one JSON object and a markdown table (see --help for where each goes).
#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
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
#include "absl/strings/str_cat.h"
#include "absl/strings/str_format.h"
#include "absl/strings/str_join.h"
#include "absl/strings/str_split.h"
#include "core/io/volume_io.h"
#include "core/mesh/mesh_io.h"
#include "core/mesh/tetrahedralize.h"
#include "core/metrics/fidelity.h"
#include "core/metrics/fidelity_json.h"
#include "core/render/camera.h"
#include "core/render/diff.h"
#include "core/render/renderer.h"
#include "core/render/transfer_function.h"
#include "core/segment/segment.h"
#include "core/simplify/simplify.h"
#include "core/volume/phantom.h"
#include "tests/bench/bench_util.h"

namespace decima {
namespace {

using bench::LoadAverage;
using bench::ParsePhantom;

namespace fs = std::filesystem;
using Json = nlohmann::ordered_json;

double MaxRssMb(const rusage& usage) { return usage.ru_maxrss / 1024.0; }  // Linux: kilobytes

double SelfPeakRssMb() {
  rusage usage{};
  getrusage(RUSAGE_SELF, &usage);
  return MaxRssMb(usage);
}

// Resident memory now (not the peak), from /proc/self/statm.
double CurrentRssMb() {
  std::ifstream statm("/proc/self/statm");
  long pages = 0, resident = 0;
  statm >> pages >> resident;
  return double(resident) * double(sysconf(_SC_PAGESIZE)) / (1024.0 * 1024.0);
}

double Median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v.empty() ? 0 : v[v.size() / 2];
}

double SecondsSince(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

struct CompareOptions {
  std::string input;
  int regions = 3;
  std::vector<double> reductions = {0.5, 0.8, 0.9, 0.95};
  std::vector<std::string> policies = {"field", "paper"};
  std::string interfaces = InterfaceModeName(SimplifyOptions().interfaces);  // field policy
  int repeat = 3;
  int size = 512;
  std::string view = "anterior";
  std::string preset = "auto";
  bool vtk = true;
  std::string python;
  std::string script = DECIMA_VTK_SCRIPT;
  std::string work_dir;
  bool keep_files = false;
};

// Everything measured once before the methods run; forked children inherit it.
struct Reference {
  Volume image;
  std::optional<Volume> labels;
  std::vector<float> interface_distance;
  TetMesh original;
  Camera camera;
  TransferFunction tf;
  std::string preset;
  RenderedImage original_image;
};

absl::Status Prepare(const CompareOptions& o, Reference& ref, Json& out) {
  auto start = std::chrono::steady_clock::now();
  auto phantom_dims = ParsePhantom(o.input);
  if (!phantom_dims.ok()) return phantom_dims.status();
  if (phantom_dims->has_value()) {
    HeadPhantomOptions p;  // the phantom decima-bench uses
    p.dims = **phantom_dims;
    p.region_means = {0, 1000, 400};
    p.noise_sigma = 50;
    auto phantom = MakeHeadPhantom(p);
    if (!phantom.ok()) return phantom.status();
    ref.image = std::move(phantom->image);
    ref.labels = std::move(phantom->labels);
    if (absl::Status s = ComputeInterfaceDistance(*ref.labels, &ref.interface_distance, nullptr);
        !s.ok())
      return s;
    out["labels"] = "phantom ground truth";
  } else {
    auto v = io::ReadVolume(o.input);
    if (!v.ok()) return v.status();
    ref.image = *std::move(v);
    SegmentOptions so;
    so.regions = o.regions;
    auto seg = Segment(ref.image, so, nullptr, nullptr);
    if (!seg.ok()) return seg.status();
    ref.labels = std::move(seg->labels);
    ref.interface_distance = std::move(seg->interface_distance_voxels);
    out["labels"] = absl::StrCat("Segment, ", o.regions, " regions");
  }
  out["dims"] = ref.image.dims;
  out["load_and_label_seconds"] = SecondsSince(start);

  start = std::chrono::steady_clock::now();
  TetrahedralizeOptions to;
  to.labels = &*ref.labels;
  to.interface_distance = ref.interface_distance.data();
  auto mesh = Tetrahedralize(ref.image, to);
  if (!mesh.ok()) return mesh.status();
  ref.original = *std::move(mesh);
  out["tetrahedralize_seconds"] = SecondsSince(start);
  out["vertices"] = ref.original.vertex_count();
  out["cells"] = ref.original.tet_count();
  start = std::chrono::steady_clock::now();
  const FaceCounts faces = CountFaces(ref.original);
  out["count_faces_seconds"] = SecondsSince(start);  // the conformity metric's own cost
  out["boundary_faces"] = faces.boundary_faces;
  out["boundary_area_mm2"] = faces.boundary_area_mm2;
  out["min_dihedral_deg"] = MeasureQuality(ref.original, 0).min_dihedral_deg;

  // The original's render; its bounds fix the camera of every render, so pixels correspond.
  auto view = ParseView(o.view);
  if (!view.ok()) return view.status();
  auto renderable = BuildRenderableMesh(ref.original);
  if (!renderable.ok()) return renderable.status();
  ViewOptions vo;
  vo.width = vo.height = o.size;
  auto camera = MakeViewCamera(*view, renderable->bounds, vo);
  if (!camera.ok()) return camera.status();
  ref.camera = *camera;
  ref.preset = o.preset;
  if (ref.preset == "auto") {  // decima-bench's rule
    const bool ct = ref.image.modality == "CT" || renderable->scalar_range.max > 1500;
    ref.preset = ct ? "ct" : "mri-t1";
  }
  auto tf = TransferFunctionPreset(ref.preset, renderable->scalar_range);
  if (!tf.ok()) return tf.status();
  ref.tf = *tf;
  auto image = Render(*renderable, ref.camera, ref.tf);
  if (!image.ok()) return image.status();
  ref.original_image = *std::move(image);
  return absl::OkStatus();
}

// MeasureFidelity and the render diff of `mesh` against the reference, as JSON fields of `out`.
// Without labels in the mesh (VTK's output), Dice and the label mismatch are null: the mesh has
// nothing to compare with the truth. Interface RMSE needs only the truth labels and stays.
void Measure(const Reference& ref, const TetMesh& mesh, bool mesh_has_labels,
             const TetMesh* original, const std::vector<int32_t>* vertex_map, Json& out) {
  FidelityOptions fo;
  fo.labels = &*ref.labels;
  fo.original = original;
  fo.vertex_map = vertex_map;
  auto f = MeasureFidelity(ref.image, mesh, fo);
  if (!f.ok()) {
    out["fidelity_error"] = f.status().ToString();
  } else {
    Json j = FidelityToJson(*f);
    if (!mesh_has_labels) {
      j["dice"] = nullptr;
      j["mean_dice"] = nullptr;
      j["label_mismatch"] = nullptr;
    }
    if (vertex_map == nullptr) {
      j["feature_vertices"] = nullptr;
      j["feature_vertices_moved"] = nullptr;
      j["feature_vertices_removed"] = nullptr;
    }
    out["fidelity"] = j;
  }
  auto renderable = BuildRenderableMesh(mesh);
  if (!renderable.ok()) {
    out["diff1"] = nullptr;
    out["render_error"] = renderable.status().ToString();
    return;
  }
  auto image = Render(*renderable, ref.camera, ref.tf);
  if (!image.ok()) {
    out["diff1"] = nullptr;
    out["render_error"] = image.status().ToString();
    return;
  }
  auto diff = Diff(ref.original_image, *image);
  if (!diff.ok()) {
    out["diff1"] = nullptr;
    out["render_error"] = diff.status().ToString();
    return;
  }
  out["diff1"] = diff->diff1;
  out["max_diff2"] = diff->max_diff2;
}

// Runs `fn` in a forked child and returns the JSON it produced, plus the child's max RSS over its
// whole life (simplify, metrics and render) as "child_max_rss_mb" (from wait4).
Json RunInChild(const std::function<Json()>& fn) {
  Json result;
  int fds[2];
  if (pipe(fds) != 0) return Json{{"error", absl::StrCat("pipe: ", std::strerror(errno))}};
  std::cout.flush();
  std::cerr.flush();
  const pid_t pid = fork();
  if (pid < 0) return Json{{"error", absl::StrCat("fork: ", std::strerror(errno))}};
  if (pid == 0) {
    close(fds[0]);
    std::string text;
    try {
      text = fn().dump();
    } catch (const std::exception& e) {
      text = Json{{"error", e.what()}}.dump();
    }
    for (size_t done = 0; done < text.size();) {
      const ssize_t n = write(fds[1], text.data() + done, text.size() - done);
      if (n <= 0) _exit(3);
      done += size_t(n);
    }
    close(fds[1]);
    _exit(0);  // no destructors or atexit handlers of the parent's objects
  }
  close(fds[1]);
  std::string text;
  char buffer[65536];
  for (ssize_t n; (n = read(fds[0], buffer, sizeof buffer)) != 0;) {
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) break;
    text.append(buffer, size_t(n));
  }
  close(fds[0]);
  int status = 0;
  rusage usage{};
  while (wait4(pid, &status, 0, &usage) < 0 && errno == EINTR) {
  }
  if (!WIFEXITED(status) || WEXITSTATUS(status) != 0 || text.empty()) {
    return Json{{"error",
                 absl::StrCat(
                     "measuring child died (status ", status,
                     WIFSIGNALED(status) ? absl::StrCat(", signal ", WTERMSIG(status)) : "", ")")}};
  }
  result = Json::parse(text, nullptr, /*allow_exceptions=*/false);
  if (result.is_discarded()) return Json{{"error", "measuring child sent malformed JSON"}};
  result["child_max_rss_mb"] = MaxRssMb(usage);
  return result;
}

Json RunDecima(const CompareOptions& o, const Reference& ref, const std::string& name,
               double reduction) {
  Json head{{"method", name}, {"kind", "decima"}, {"target_reduction", reduction}};
  if (name == "field") head["interfaces"] = o.interfaces;
  const std::optional<SimplifyPolicy> policy = ParseSimplifyPolicy(name);
  if (!policy) {
    head["error"] =
        absl::StrCat("unknown policy '", name, "' (this build knows: ", SimplifyPolicyNames(), ")");
    return head;
  }
  Json r = RunInChild([&]() -> Json {
    // What the child holds before simplifying: the inherited volume, labels and original mesh
    // (anonymous pages count once copied at the fork; shared-library pages only once touched,
    // so this is below the parent's RSS).
    const double rss_before = CurrentRssMb();
    SimplifyOptions so;
    so.policy = *policy;
    so.target_reduction = reduction;
    so.interfaces = *ParseInterfaceMode(o.interfaces);  // the flag accepts only known names
    std::optional<SimplifyResult> result;
    std::vector<double> runs;
    for (int i = 0; i < o.repeat; ++i) {
      result.reset();  // one result alive at a time, as the pipeline holds it
      const auto start = std::chrono::steady_clock::now();
      auto s = Simplify(ref.original, so);
      runs.push_back(SecondsSince(start));
      if (!s.ok()) return Json{{"error", s.status().ToString()}};
      result = *std::move(s);
    }
    Json out;
    out["seconds"] = Median(runs);
    out["seconds_all"] = runs;
    out["peak_rss_mb"] = SelfPeakRssMb();  // before measuring: the simplification's own peak
    out["rss_before_simplify_mb"] = rss_before;
    out["peak_rss_delta_mb"] = out["peak_rss_mb"].get<double>() - rss_before;
    out["cells"] = result->output_cells;
    out["achieved_reduction"] = result->achieved_reduction;
    out["reached_target"] = result->reached_target;
    out["stop_reason"] = StopReasonName(result->stop_reason);
    out["stop_message"] = result->stop_message;
    Measure(ref, result->mesh, /*mesh_has_labels=*/true, &ref.original, &result->vertex_map, out);
    return out;
  });
  head.update(r);
  return head;
}

// Runs `argv` with stdout captured; returns its exit status, stdout, wall seconds and max RSS.
struct ChildRun {
  int status = -1;
  std::string out;
  double wall_seconds = 0;
  double max_rss_mb = 0;
  std::string error;
};
ChildRun RunProcess(const std::vector<std::string>& argv) {
  ChildRun run;
  int fds[2];
  if (pipe(fds) != 0) {
    run.error = absl::StrCat("pipe: ", std::strerror(errno));
    return run;
  }
  std::vector<char*> args;
  for (const std::string& a : argv) args.push_back(const_cast<char*>(a.c_str()));
  args.push_back(nullptr);
  std::cout.flush();
  std::cerr.flush();
  const auto start = std::chrono::steady_clock::now();
  const pid_t pid = fork();
  if (pid < 0) {
    run.error = absl::StrCat("fork: ", std::strerror(errno));
    return run;
  }
  if (pid == 0) {
    dup2(fds[1], STDOUT_FILENO);
    close(fds[0]);
    close(fds[1]);
    execvp(args[0], args.data());
    std::fprintf(stderr, "decima-compare: cannot run %s: %s\n", args[0], std::strerror(errno));
    _exit(127);
  }
  close(fds[1]);
  char buffer[4096];
  for (ssize_t n; (n = read(fds[0], buffer, sizeof buffer)) != 0;) {
    if (n < 0 && errno == EINTR) continue;
    if (n < 0) break;
    run.out.append(buffer, size_t(n));
  }
  close(fds[0]);
  rusage usage{};
  while (wait4(pid, &run.status, 0, &usage) < 0 && errno == EINTR) {
  }
  run.wall_seconds = SecondsSince(start);
  run.max_rss_mb = MaxRssMb(usage);
  return run;
}

Json RunVtk(const CompareOptions& o, const Reference& ref, const fs::path& original_vtu,
            const fs::path& dir, double reduction) {
  Json out{{"method", "vtk-quadric"}, {"kind", "vtk"}, {"target_reduction", reduction}};
  const fs::path result = dir / absl::StrFormat("vtk-%.3f.vtu", reduction);
  std::vector<double> execute, wall, rss;
  Json last;
  for (int i = 0; i < o.repeat; ++i) {
    ChildRun run = RunProcess({o.python, o.script, original_vtu.string(), result.string(),
                               absl::StrFormat("%.17g", reduction), "scalar"});
    if (!run.error.empty() || !WIFEXITED(run.status) || WEXITSTATUS(run.status) != 0) {
      out["error"] = absl::StrCat("VTK run failed (", run.error.empty() ? "" : run.error + ", ",
                                  "status ", run.status, "); see its messages above");
      return out;
    }
    last = Json::parse(run.out, nullptr, false);
    if (last.is_discarded() || !last.contains("execute_seconds")) {
      out["error"] = "the VTK script printed no JSON: " + run.out.substr(0, 200);
      return out;
    }
    execute.push_back(last["execute_seconds"].get<double>());
    wall.push_back(run.wall_seconds);
    rss.push_back(run.max_rss_mb);
  }
  out["seconds"] = Median(execute);
  out["seconds_all"] = execute;
  out["subprocess_wall_seconds"] = Median(wall);
  out["subprocess_wall_seconds_all"] = wall;
  out["peak_rss_mb"] = *std::max_element(rss.begin(), rss.end());
  out["vtk_last_run"] = last;  // the script's own report of the last of the --repeat runs
  // VTK's output may hold flat cells (ch2 MRI at 80 %): keep them so they are measured and
  // counted (inverted / degenerate cells) instead of failing the row.
  VtuReadReport report;
  auto mesh = ReadVtu(result, &report, {.allow_inverted_cells = true});
  if (!mesh.ok()) {
    out["error"] = absl::StrCat("reading VTK's output: ", mesh.status().ToString());
    return out;
  }
  out["cells"] = mesh->tet_count();
  out["achieved_reduction"] =
      1.0 - double(mesh->tet_count()) / double(std::max<int64_t>(1, ref.original.tet_count()));
  out["field_array"] = report.scalar_array;
  out["inverted_or_flat_cells"] = report.inverted_or_flat_cells;
  out["labels"] = report.has_labels ? "from the file"
                                    : "none in VTK's output: Dice and label mismatch are null";
  Measure(ref, *mesh, report.has_labels, nullptr, nullptr, out);
  return out;
}

std::string Fixed(const Json& v, int digits) {
  if (v.is_null() || !v.is_number()) return "—";
  return absl::StrFormat("%.*f", digits, v.get<double>());
}

// 2096770 -> "2,096,770".
std::string Thousands(int64_t n) {
  std::string digits = absl::StrCat(n < 0 ? -n : n), out;
  for (size_t i = 0; i < digits.size(); ++i) {
    if (i > 0 && (digits.size() - i) % 3 == 0) out += ',';
    out += digits[i];
  }
  return n < 0 ? "-" + out : out;
}

std::string Markdown(const Json& result) {
  std::ostringstream md;
  md << "| method | target | cells | removed | seconds | peak RSS MB | PSNR dB | coverage | "
        "mean Dice | interface RMSE | diff1 | min dihedral ° | non-manifold faces | "
        "folded faces | boundary area / original |\n"
     << "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n";
  const double area = result["original"]["boundary_area_mm2"].get<double>();
  for (const Json& r : result["results"]) {
    md << "| " << r["method"].get<std::string>() << " | "
       << absl::StrFormat("%.0f %%", 100 * r["target_reduction"].get<double>()) << " | ";
    if (r.contains("error") && !r.contains("fidelity")) {
      md << "error: " << r["error"].get<std::string>() << " |||||||||||||\n";
      continue;
    }
    const Json f = r.value("fidelity", Json::object());
    auto num = [&](const char* key) { return f.contains(key) ? f[key] : Json(); };
    md << (r.contains("cells") ? Thousands(r["cells"].get<int64_t>()) : "—") << " | "
       << Fixed(r.value("achieved_reduction", Json()).is_number()
                    ? Json(100 * r["achieved_reduction"].get<double>())
                    : Json(),
                1)
       << " % | " << Fixed(r.value("seconds", Json()), 2) << " | "
       << Fixed(r.value("peak_rss_mb", Json()), 0) << " | " << Fixed(num("psnr_db"), 1) << " | "
       << Fixed(num("coverage"), 3) << " | " << Fixed(num("mean_dice"), 4) << " | "
       << Fixed(num("interface_rmse"), 1) << " | " << Fixed(r.value("diff1", Json()), 3) << " | "
       << Fixed(num("min_dihedral_deg"), 3) << " | "
       << (num("nonmanifold_faces").is_number()
               ? absl::StrCat(num("nonmanifold_faces").get<int64_t>())
               : "—")
       << " | "
       << (num("folded_faces").is_number() ? absl::StrCat(num("folded_faces").get<int64_t>()) : "—")
       << " | "
       << (num("boundary_area_mm2").is_number() && area > 0
               ? absl::StrFormat("%.4f", num("boundary_area_mm2").get<double>() / area)
               : "—")
       << " |\n";
  }
  return md.str();
}

std::string DefaultPython() {
  // Debian's python3-vtk9 lives in /usr/bin/python3, which a pyenv or venv python3 earlier on
  // PATH may hide; $DECIMA_PYTHON overrides (as in the mesh tests).
  if (const char* env = std::getenv("DECIMA_PYTHON")) return env;
  if (fs::exists("/usr/bin/python3")) return "/usr/bin/python3";
  return "python3";
}

int Main(int argc, char** argv) {
  CLI::App app{
      "decima-compare: Decima's simplification policies against VTK's quadric decimation "
      "(vtkUnstructuredGridQuadricDecimation) on the same mesh, measured by the same code.\n"
      "Output: the JSON object goes to stdout (or --json FILE), the markdown table to stderr "
      "after the progress lines (or --markdown FILE).\n"
      "Seconds: median of --repeat runs of the simplification alone (Decima: Simplify(); VTK: "
      "the filter's Update() inside the python script; the whole subprocess's wall time is "
      "subprocess_wall_seconds). Peak RSS: Decima runs each (policy, reduction) in a forked "
      "child and reports the child's peak after simplifying, which includes the volume, labels "
      "and original mesh it inherited (rss_before_simplify_mb; peak_rss_delta_mb is the "
      "difference); "
      "VTK reports the python child's max RSS (wait4), which includes reading the .vtu.\n"
      "Dice: VTK's output has no labels, so its Dice is null; PSNR, coverage, interface RMSE, "
      "diff1, quality and manifoldness are measured for every method."};
  CompareOptions o;
  o.python = DefaultPython();
  std::string reductions_arg = "0.5,0.8,0.9,0.95", policies_arg = "field,paper", json_path, md_path;
  app.add_option("--input", o.input, "Volume file, DICOM folder, or phantom:NxNxN (synthetic head)")
      ->required();
  app.add_option("--reductions", reductions_arg, "Comma-separated fractions of cells to remove")
      ->capture_default_str();
  app.add_option("--policies", policies_arg,
                 "Comma-separated Decima policies (this build: " + SimplifyPolicyNames() +
                     "); an unknown name gives an error entry, not a failure")
      ->capture_default_str();
  app.add_option("--interfaces", o.interfaces,
                 "field policy: free (interface vertices move wherever every voxel centre keeps "
                 "its label) or voxel-faces (the voxel staircase kept as a set)")
      ->check(CLI::IsMember({"free", "voxel-faces"}))
      ->capture_default_str();
  app.add_option("--repeat", o.repeat,
                 "Timed runs per method and reduction; the median is reported")
      ->check(CLI::Range(1, 100))
      ->capture_default_str();
  app.add_option("--regions", o.regions, "Segmentation regions K (files; phantoms use their truth)")
      ->check(CLI::Range(2, 8))
      ->capture_default_str();
  app.add_option("--size", o.size, "Render width and height in pixels")
      ->check(CLI::Range(16, 4096))
      ->capture_default_str();
  app.add_option("--view", o.view, "Render view preset")->capture_default_str();
  app.add_option("--preset", o.preset,
                 "Transfer-function preset: ct, ct-bone, mri-t1, or auto (ct for CT data)")
      ->capture_default_str();
  app.add_flag("!--no-vtk", o.vtk, "Skip VTK (Decima policies only)");
  app.add_option("--python", o.python, "Python with the vtk module ($DECIMA_PYTHON)")
      ->capture_default_str();
  app.add_option("--vtk-script", o.script, "The VTK side (tests/bench/vtk_quadric_decimate.py)")
      ->capture_default_str();
  app.add_option("--work-dir", o.work_dir,
                 "Folder for the exported and decimated .vtu files (default: a new temporary "
                 "folder, removed at the end unless --keep-files)");
  app.add_flag("--keep-files", o.keep_files, "Keep the .vtu files");
  app.add_option("--json", json_path, "Write the JSON object to FILE instead of stdout");
  app.add_option("--markdown", md_path, "Write the markdown table to FILE instead of stderr");
  CLI11_PARSE(app, argc, argv);

  o.reductions.clear();
  for (absl::string_view part : absl::StrSplit(reductions_arg, ',', absl::SkipEmpty())) {
    double r = 0;
    if (!absl::SimpleAtod(part, &r) || !(r > 0 && r < 1)) {
      std::cerr << "decima-compare: --reductions: '" << part << "' is not in (0, 1)\n";
      return 2;
    }
    o.reductions.push_back(r);
  }
  o.policies = absl::StrSplit(policies_arg, ',', absl::SkipEmpty());
  if (o.reductions.empty()) {
    std::cerr << "decima-compare: --reductions is empty\n";
    return 2;
  }

  Json result;
  result["command"] = absl::StrJoin(argv, argv + argc, " ");
  result["input"] = o.input;
  result["repeat"] = o.repeat;
  result["machine"] = {{"cores", std::thread::hardware_concurrency()},
                       {"load_average_1m_at_start", LoadAverage()}};
  result["render"] = {{"view", o.view}, {"size", o.size}};
  result["peak_rss"] =
      "decima: forked child per (policy, reduction), peak after Simplify including the inherited "
      "volume and original mesh (rss_before_simplify_mb); vtk: python child's max RSS (wait4), "
      "including python, VTK and the .vtu it read";

  Reference ref;
  Json original;
  std::cerr << "decima-compare: loading, labelling and tetrahedralizing " << o.input << "\n";
  if (absl::Status s = Prepare(o, ref, original); !s.ok()) {
    std::cerr << "decima-compare: " << s << "\n";
    return 1;
  }
  result["render"]["preset"] = ref.preset;
  result["original"] = original;

  fs::path dir = o.work_dir;
  const bool temporary = dir.empty();
  if (temporary) {
    std::string pattern = (fs::temp_directory_path() / "decima-compare-XXXXXX").string();
    if (mkdtemp(pattern.data()) == nullptr) {
      std::cerr << "decima-compare: mkdtemp: " << std::strerror(errno) << "\n";
      return 1;
    }
    dir = pattern;
  } else {
    std::error_code ec;
    fs::create_directories(dir, ec);
  }
  const fs::path original_vtu = dir / "original.vtu";
  if (o.vtk) {
    if (absl::Status s = WriteVtu(ref.original, original_vtu); !s.ok()) {
      std::cerr << "decima-compare: " << s << "\n";
      std::error_code ec;
      if (temporary) fs::remove_all(dir, ec);  // leave no half-written export behind
      return 1;
    }
  }

  Json results = Json::array();
  for (double reduction : o.reductions) {
    for (const std::string& policy : o.policies) {
      std::cerr << "decima-compare: " << policy << " at " << reduction << "\n";
      results.push_back(RunDecima(o, ref, policy, reduction));
    }
    if (o.vtk) {
      std::cerr << "decima-compare: vtk-quadric at " << reduction << "\n";
      results.push_back(RunVtk(o, ref, original_vtu, dir, reduction));
    }
  }
  result["results"] = results;
  result["machine"]["load_average_1m_at_end"] = LoadAverage();
  result["parent_peak_rss_mb"] = SelfPeakRssMb();
  if (temporary && !o.keep_files) {
    std::error_code ec;
    fs::remove_all(dir, ec);
  } else {
    result["work_dir"] = dir.string();
  }

  const std::string md = Markdown(result);
  if (json_path.empty()) {
    std::cout << result.dump(2) << std::endl;
  } else {
    std::ofstream(json_path) << result.dump(2) << "\n";
  }
  if (md_path.empty()) {
    std::cerr << "\n" << md;
  } else {
    std::ofstream(md_path) << md;
  }
  return 0;
}

}  // namespace
}  // namespace decima

int main(int argc, char** argv) { return decima::Main(argc, argv); }
