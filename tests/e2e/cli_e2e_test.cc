// The `decima` CLI as a user meets it (issue 15), through the real server and client processes:
// chosen artifacts, the end-of-watch summary and its exit code, tables and -o, delete/prune,
// --version, id prefixes, fail-fast on a wrong address, plain progress lines, Ctrl-C, inputs
// (.mhd + data, DICOM folders with stray files, "AZ:EL" views, reused request ids), the
// pictures' text chunks and report.html in headless Chromium.
#include <grpcpp/grpcpp.h>
#include <png.h>
#include <signal.h>
#include <sys/inotify.h>
#include <unistd.h>

#include <cstring>
#include <fstream>
#include <nlohmann/json.hpp>
#include <regex>
#include <set>
#include <sstream>
#include <thread>

#include "absl/strings/match.h"
#include "absl/strings/str_cat.h"
#include "absl/strings/str_split.h"
#include "core/io/png.h"
#include "decima/v1/jobs.grpc.pb.h"
#include "decima/v1/volumes.grpc.pb.h"
#include "gmock/gmock.h"
#include "gtest/gtest.h"
#include "tests/e2e/e2e_util.h"
#include "tests/testing/test_data.h"

namespace decima::e2e {
namespace {
namespace fs = std::filesystem;
using ::testing::HasSubstr;
using ::testing::Not;
using namespace std::chrono_literals;

std::string ReadFile(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

std::set<std::string> FilesIn(const fs::path& dir) {
  std::set<std::string> out;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(dir, ec)) out.insert(e.path().filename().string());
  return out;
}

std::vector<std::string> Lines(const std::string& s) {
  std::vector<std::string> out;
  std::istringstream in(s);
  for (std::string l; std::getline(in, l);) out.push_back(l);
  return out;
}

// The summary line "reduction: A% of the cells removed (target T%), B -> C cells": A must be
// what B and C say, to one decimal, and at least the target. The last collapse may remove a few
// cells more than the target asks.
void ExpectReductionLine(const std::string& text, double target_percent) {
  static const std::regex line(
      R"(reduction: ([0-9]+\.[0-9])% of the cells removed \(target ([0-9]+\.[0-9])%\), ([0-9]+) -> ([0-9]+) cells)");
  std::smatch m;
  if (!std::regex_search(text, m, line)) {
    ADD_FAILURE() << "no reduction line in:\n" << text;
    return;
  }
  const double achieved = std::stod(m[1]), before = std::stod(m[3]), after = std::stod(m[4]);
  EXPECT_DOUBLE_EQ(std::stod(m[2]), target_percent);
  EXPECT_GE(achieved, target_percent);
  EXPECT_NEAR(achieved, 100.0 * (1.0 - after / before), 0.05 + 1e-9);
}

int CountOf(const std::string& s, const std::string& what) {
  int n = 0;
  for (size_t at = s.find(what); at != std::string::npos; at = s.find(what, at + 1)) ++n;
  return n;
}

std::vector<v1::Volume> ListVolumes(const std::string& address) {
  auto stub =
      v1::Volumes::NewStub(grpc::CreateChannel(address, grpc::InsecureChannelCredentials()));
  grpc::ClientContext ctx;
  ctx.set_deadline(std::chrono::system_clock::now() + 30s);
  v1::ListVolumesRequest req;
  v1::ListVolumesResponse resp;
  EXPECT_TRUE(stub->ListVolumes(&ctx, req, &resp).ok());
  return {resp.volumes().begin(), resp.volumes().end()};
}

class CliE2E : public ScratchTest {
 protected:
  CliE2E() : ScratchTest("cli_e2e") {}

  // Two succeeded jobs of the phantom (30 % reduction), oldest first, as bare ids.
  std::vector<std::string> TwoSucceededJobs(const ServerProcess& server) {
    std::vector<std::string> jobs;
    for (int i = 0; i < 2; ++i) {
      CliResult r = RunCli(server.address(), {"-q", "submit", volume_.string(), "--watch",
                                              "--image-size", "32", "--reduction", "0.3"});
      EXPECT_EQ(r.rc, 0) << r.err;
      jobs.push_back(FirstLine(r.out).substr(5));
    }
    return jobs;
  }
};

// Issue 35 part 5: `--request-id` hashed its text through a file at a predictable path in the
// temp folder (decima-id-<pid>, std::ofstream): a symlink planted there made root's CLI
// overwrite its target, a FIFO made it hang. The CLI now makes no file there at all: watched
// with inotify, its TMPDIR sees no file created during a submit with --request-id.
TEST_F(CliE2E, SubmitWithARequestIdCreatesNoFileInTheTempFolder) {
  ServerProcess server(scratch_ / "data");
  const fs::path tmp = scratch_ / "tmp";
  fs::create_directories(tmp);
  int in = inotify_init1(IN_NONBLOCK | IN_CLOEXEC);
  ASSERT_GE(in, 0);
  ASSERT_GE(inotify_add_watch(in, tmp.c_str(), IN_CREATE | IN_MOVED_TO), 0);
  CliResult r = RunCli(server.address(),
                       {"submit", volume_.string(), "--request-id", "nightly-42", "--image-size",
                        "32", "--reduction", "0.3"},
                       std::chrono::seconds(60), {{"TMPDIR", tmp.string()}});
  ASSERT_EQ(r.rc, 0) << r.err << server.Log();
  std::vector<std::string> created;
  alignas(inotify_event) char buf[4096];
  for (ssize_t n; (n = read(in, buf, sizeof buf)) > 0;) {
    for (char* p = buf; p < buf + n;) {
      auto* ev = reinterpret_cast<inotify_event*>(p);
      if (ev->len > 0) created.push_back(ev->name);
      p += sizeof(inotify_event) + ev->len;
    }
  }
  close(in);
  EXPECT_THAT(created, ::testing::IsEmpty());
  // The same request id finds the same volume and job (the id's hash is as before).
  CliResult again =
      RunCli(server.address(), {"submit", volume_.string(), "--request-id", "nightly-42",
                                "--image-size", "32", "--reduction", "0.3"});
  ASSERT_EQ(again.rc, 0) << again.err;
  EXPECT_EQ(FirstLine(again.out), FirstLine(r.out));
}

// Issue 35 part 7: a display name (here the name of the submitted file) with escape sequences
// reached an admin's terminal through `decima list`; every server-provided string is escaped.
TEST_F(CliE2E, EscapeSequencesInADisplayNameDoNotReachTheTerminal) {
  ServerProcess server(scratch_ / "data");
  CliResult r = RunCli(server.address(), {"submit", volume_.string(), "--image-size", "32"});
  ASSERT_EQ(r.rc, 0) << r.err << server.Log();
  // Another volume of the same blob whose display name is an attack on terminals (set OSC
  // title, clear screen, an 8-bit CSI as UTF-8), and a job on it. The file has another name:
  // under the same one this caller's volume would be reused, with its first display name.
  auto volumes = v1::Volumes::NewStub(SharedChannel(server.address()));
  auto jobs = v1::Jobs::NewStub(SharedChannel(server.address()));
  const v1::Job first = GetJob(server.address(), FirstLine(r.out));
  v1::Volume vol;
  {
    grpc::ClientContext ctx;
    v1::GetVolumeRequest g;
    g.set_name(first.spec().volume());
    ASSERT_TRUE(volumes->GetVolume(&ctx, g, &vol).ok());
  }
  v1::CreateVolumeRequest cv;
  *cv.mutable_volume()->mutable_files() = vol.files();
  cv.mutable_volume()->mutable_files(0)->set_path("scan.nii");
  cv.mutable_volume()->set_display_name("\x1b]0;owned\x07\x1b[2Jscan\xc2\x9b.nii");
  v1::Volume evil;
  {
    grpc::ClientContext ctx;
    grpc::Status st = volumes->CreateVolume(&ctx, cv, &evil);
    ASSERT_TRUE(st.ok()) << st.error_message();
  }
  v1::CreateJobRequest cj;
  *cj.mutable_spec() = first.spec();
  cj.mutable_spec()->set_volume(evil.name());
  v1::Job job;
  {
    grpc::ClientContext ctx;
    grpc::Status st = jobs->CreateJob(&ctx, cj, &job);
    ASSERT_TRUE(st.ok()) << st.error_message();
  }
  for (const std::vector<std::string>& cmd :
       {std::vector<std::string>{"list"}, {"list", "-o", "wide"}, {"status", job.name()}}) {
    CliResult l = RunCli(server.address(), cmd);
    ASSERT_EQ(l.rc, 0) << l.err;
    EXPECT_THAT(l.out, HasSubstr("\\x1b]0;owned\\x07\\x1b[2Jscan\\u009b.nii")) << cmd[0];
    EXPECT_EQ(l.out.find('\x1b'), std::string::npos) << cmd[0];
    EXPECT_EQ(l.out.find("\xc2\x9b"), std::string::npos) << cmd[0];
  }
}

// Issue 35 part 7: `prune --force` on an emptied server left 147 MB (uploads in their grace
// period, the disk reserve, the WAL) without a word; it now says what stays and why.
TEST_F(CliE2E, PruneForceSaysWhatTheServerKeepsForNow) {
  ServerProcess server(scratch_ / "data");
  CliResult r =
      RunCli(server.address(), {"submit", volume_.string(), "--image-size", "32", "--watch"});
  ASSERT_EQ(r.rc, 0) << r.err << server.Log();
  CliResult dry = RunCli(server.address(), {"prune"});
  ASSERT_EQ(dry.rc, 0) << dry.err;
  EXPECT_THAT(dry.err, ::testing::Not(HasSubstr("--blob-grace-seconds")));
  CliResult p = RunCli(server.address(), {"prune", "--force"});
  ASSERT_EQ(p.rc, 0) << p.err;
  EXPECT_THAT(p.err, HasSubstr("deleted 1 job(s)"));
  EXPECT_THAT(p.err, HasSubstr("--blob-grace-seconds"));
  EXPECT_THAT(p.err, HasSubstr("--disk-reserve-mb"));
}

TEST_F(CliE2E, DefaultArtifactsAreSmallOutputsAreChosenAndFetchOnlyPicks) {
  ServerProcess server(scratch_ / "data");
  // Default: no .msh, a report and the segmentation figure.
  const fs::path def = scratch_ / "default";
  CliResult r = RunCli(server.address(), {"submit", volume_.string(), "--out", def.string(),
                                          "--image-size", "64", "--reduction", "0.3"});
  ASSERT_EQ(r.rc, 0) << r.err << server.Log();
  EXPECT_EQ(FilesIn(def),
            (std::set<std::string>{"mesh.vtu", "labels.nii.gz", "original.png", "simplified.png",
                                   "diff.png", "comparison.png", "segmentation.png", "metrics.json",
                                   "report.html"}));
  // The summary of the end of the watch: achieved reduction, sizes, ratio.
  ExpectReductionLine(r.err, 30.0);
  EXPECT_THAT(r.err, HasSubstr("x the input's bytes"));

  // Only the meshes asked for, in any case, an uncompressed .vtu.
  const fs::path chosen = scratch_ / "chosen";
  r = RunCli(server.address(),
             {"submit", volume_.string(), "--outputs", "VTU,msh", "--vtu-level", "0", "--out",
              chosen.string(), "--image-size", "64", "--reduction", "0.3"});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_EQ(FilesIn(chosen), (std::set<std::string>{"mesh.vtu", "mesh.msh", "metrics.json"}));
  const std::string vtu = ReadFile(chosen / "mesh.vtu");
  EXPECT_THAT(vtu, Not(HasSubstr("compressor=")));
  EXPECT_THAT(ReadFile(def / "mesh.vtu"), HasSubstr("compressor=\"vtkZLibDataCompressor\""));
  const std::string job = FirstLine(r.out);

  // --mesh-compression lzma reaches the file's header (VTK's LZMA compressor); the CLI refuses
  // a name it does not know before anything is sent.
  const fs::path lzma = scratch_ / "lzma";
  CliResult l = RunCli(server.address(), {"submit", volume_.string(), "--outputs", "vtu",
                                          "--mesh-compression", "lzma", "--out", lzma.string(),
                                          "--image-size", "64", "--reduction", "0.3"});
  ASSERT_EQ(l.rc, 0) << l.err;
  const std::string lzma_vtu = ReadFile(lzma / "mesh.vtu");
  EXPECT_THAT(lzma_vtu.substr(0, lzma_vtu.find("<UnstructuredGrid>")),
              HasSubstr("compressor=\"vtkLZMADataCompressor\""));
  l = RunCli(server.address(), {"submit", volume_.string(), "--mesh-compression", "lz4"});
  EXPECT_EQ(l.rc, 2) << l.err;
  EXPECT_THAT(l.err, HasSubstr("--mesh-compression"));

  // A name the server does not know is refused at submit, naming the field.
  r = RunCli(server.address(), {"submit", volume_.string(), "--outputs", "obj"});
  EXPECT_EQ(r.rc, 2) << r.err;  // the CLI's own check
  EXPECT_THAT(r.err, HasSubstr("obj"));

  // fetch --only: file names or kinds; an unknown name lists what there is.
  const fs::path some = scratch_ / "some";
  r = RunCli(server.address(), {"fetch", job, "--out", some.string(), "--only", "vtu"});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_EQ(FilesIn(some), (std::set<std::string>{"mesh.vtu"}));
  r = RunCli(server.address(),
             {"fetch", job, "--out", some.string(), "--only", "mesh.msh", "metrics"});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_EQ(FilesIn(some), (std::set<std::string>{"mesh.vtu", "mesh.msh", "metrics.json"}));
  r = RunCli(server.address(), {"fetch", job, "--out", some.string(), "--only", "report"});
  EXPECT_EQ(r.rc, 2);
  EXPECT_THAT(r.err, HasSubstr("it has: mesh.vtu mesh.msh metrics.json"));
}

// fetch --reduction: the mesh at another reduction from a job's level record, through a level
// job of the server; byte for byte the mesh of a job run at that reduction with the record.
// A job without a record is refused with what to do.
TEST_F(CliE2E, FetchAReductionFromTheLevelRecordWithoutSimplifyingAgain) {
  ServerProcess server(scratch_ / "data");
  CliResult r = RunCli(server.address(), {"-q", "submit", volume_.string(), "--outputs",
                                          "vtu,levels", "--reduction", "0.3", "--watch"});
  ASSERT_EQ(r.rc, 0) << r.err << server.Log();
  const std::string recorded = FirstLine(r.out);
  const fs::path direct = scratch_ / "direct";
  r = RunCli(server.address(), {"-q", "submit", volume_.string(), "--outputs", "vtu,levels",
                                "--reduction", "0.6", "--out", direct.string()});
  ASSERT_EQ(r.rc, 0) << r.err;

  const fs::path level = scratch_ / "level";
  r = RunCli(server.address(), {"fetch", recorded, "--reduction", "0.6", "--out", level.string()});
  ASSERT_EQ(r.rc, 0) << r.err << server.Log();
  const std::string by = " is taken from its record by ";
  const size_t at = r.err.find("the level 0.6 of " + recorded + by);
  ASSERT_NE(at, std::string::npos) << r.err;
  const std::string level_job = FirstLine(r.err.substr(r.err.find(by, at) + by.size()));
  EXPECT_EQ(FilesIn(level), (std::set<std::string>{"mesh.vtu", "metrics.json"}));
  // Its description says where its mesh came from.
  CliResult status = RunCli(server.address(), {"status", level_job});
  EXPECT_EQ(status.rc, 0) << status.err;
  EXPECT_THAT(status.out, HasSubstr("levels_of " + recorded + " (the mesh is a level of"));
  EXPECT_EQ(ReadFile(level / "mesh.vtu"), ReadFile(direct / "mesh.vtu"));
  auto m = nlohmann::json::parse(ReadFile(level / "metrics.json"));
  EXPECT_TRUE(m["simplification"]["from_levels"].get<bool>());
  EXPECT_EQ(m["fidelity"]["label_mismatch"].get<double>(), 0.0);

  // The record's mesh kinds are chosen with --only.
  const fs::path both = scratch_ / "both";
  r = RunCli(server.address(), {"-q", "fetch", recorded, "--reduction", "0.5", "--only", "vtu",
                                "--only", "msh", "--out", both.string()});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_EQ(FilesIn(both), (std::set<std::string>{"mesh.vtu", "mesh.msh"}));

  // A job that kept no record: refused before anything is queued, saying how to get one.
  r = RunCli(server.address(), {"-q", "submit", volume_.string(), "--outputs", "vtu", "--reduction",
                                "0.3", "--watch"});
  ASSERT_EQ(r.rc, 0) << r.err;
  const std::string plain = FirstLine(r.out);
  r = RunCli(server.address(),
             {"fetch", plain, "--reduction", "0.5", "--out", (scratch_ / "none").string()});
  EXPECT_NE(r.rc, 0);
  EXPECT_THAT(r.err, HasSubstr("kept no level record (mesh.levels and labels.nii.gz)"));
  EXPECT_THAT(r.err, HasSubstr("--outputs vtu,levels"));
  r = RunCli(server.address(), {"list"});
  EXPECT_EQ(Lines(r.out).size(), 1u + 5u) << r.out;  // three submits, two level jobs
}

TEST_F(CliE2E, MissedReductionTargetWarnsAndExitsTen) {
  ServerProcess server(scratch_ / "data");
  // 99 % of a 12x10x8 phantom cannot go: the hull and the region interfaces stay.
  CliResult r = RunCli(server.address(), {"submit", volume_.string(), "--reduction", "0.99",
                                          "--watch", "--image-size", "32"});
  EXPECT_EQ(r.rc, 10) << r.err;
  EXPECT_THAT(r.err, HasSubstr("SUCCEEDED"));
  EXPECT_THAT(r.err, HasSubstr("WARNING: the reduction target was not reached"));
  // -q keeps the warning (it explains the exit code); --json adds a summary object.
  const std::string job = FirstLine(r.out);
  r = RunCli(server.address(), {"-q", "watch", job});
  EXPECT_EQ(r.rc, 10);
  EXPECT_THAT(r.err, HasSubstr("WARNING"));
  r = RunCli(server.address(), {"watch", job, "-o", "json"});
  EXPECT_EQ(r.rc, 10);
  bool summary = false;
  for (const auto& l : Lines(r.out)) {
    auto j = nlohmann::json::parse(l, nullptr, false);
    ASSERT_FALSE(j.is_discarded()) << l;
    if (j.contains("summary")) {
      summary = true;
      EXPECT_FALSE(j["summary"]["reached_target"].get<bool>());
      EXPECT_LT(j["summary"]["achieved_reduction"].get<double>(), 0.99);
    }
  }
  EXPECT_TRUE(summary) << r.out;
}

// Issue 31 item 4: a bad PSNR floor is refused by the CLI before anything is uploaded (the
// server refuses it too, tests/server/jobs/bad_job_specs.h), and no job is queued.
TEST_F(CliE2E, BadMinPsnrIsRefusedAtSubmitAndQueuesNothingAndAFloorStopIsNoWarning) {
  ServerProcess server(scratch_ / "data");
  for (const char* bad : {"--min-psnr=nan", "--min-psnr=-5", "--min-psnr=inf", "--min-psnr=0"}) {
    CliResult r = RunCli(server.address(), {"submit", volume_.string(), bad});
    EXPECT_EQ(r.rc, 2) << bad << "\n" << r.err;
    EXPECT_THAT(r.err, HasSubstr("--min-psnr")) << bad;
    EXPECT_THAT(r.err, HasSubstr("finite and > 0")) << bad;
  }
  CliResult r = RunCli(server.address(),
                       {"submit", volume_.string(), "--min-psnr", "40", "--policy", "paper"});
  EXPECT_EQ(r.rc, 2) << r.err;
  EXPECT_THAT(r.err, HasSubstr("--min-psnr needs --policy field"));
  r = RunCli(server.address(), {"list", "-o", "json"});
  EXPECT_EQ(r.rc, 0) << r.err;
  EXPECT_EQ(r.out, "") << "no job queued";
  EXPECT_TRUE(ListVolumes(server.address()).empty()) << "nothing uploaded";
  // A floor that stops the job before its target: what was asked for, so exit 0 with the stop
  // message instead of the target warning (exit 10). The phantom's regions are constant, which a
  // simplified mesh reproduces exactly (infinite PSNR): noise makes a finite floor bind.
  std::string noisy = ReadFile(volume_);
  for (size_t at = 352, k = 0; at + 1 < noisy.size(); at += 2, ++k) {  // int16 after the header
    int16_t v = 0;
    std::memcpy(&v, &noisy[at], 2);
    v = static_cast<int16_t>(v + int((k * 2654435761u) >> 27) - 16);
    std::memcpy(&noisy[at], &v, 2);
  }
  const fs::path noisy_path = scratch_ / "noisy.nii";
  std::ofstream(noisy_path, std::ios::binary) << noisy;
  r = RunCli(server.address(), {"submit", noisy_path.string(), "--min-psnr", "1e6", "--reduction",
                                "0.3", "--watch", "--image-size", "32"});
  EXPECT_EQ(r.rc, 0) << r.err;
  EXPECT_THAT(r.err, HasSubstr("stopped by the PSNR floor: PSNR floor 1e+06 dB: kept "));
  EXPECT_THAT(r.err, Not(HasSubstr("WARNING")));
  r = RunCli(server.address(), {"status", FirstLine(r.out)});
  EXPECT_EQ(r.rc, 0) << r.err;
  EXPECT_THAT(r.out, HasSubstr("min_psnr 1e+06 dB"));
}

// Issue 30: --stream-slab-voxels reaches the pipeline through the API: the job is simplified in
// slabs (its progress counts them, status and metrics.json say so), every voxel keeps its label;
// a depth the pipeline cannot run is refused before anything is uploaded, and one the spec
// cannot use (a PSNR floor) by the server, naming the field.
TEST_F(CliE2E, StreamSlabVoxelsSimplifiesInSlabsAndBadDepthsAreRefused) {
  ServerProcess server(scratch_ / "data");
  for (const char* bad : {"--stream-slab-voxels=3", "--stream-slab-voxels=-1"}) {
    CliResult r = RunCli(server.address(), {"submit", volume_.string(), bad});
    EXPECT_EQ(r.rc, 2) << bad << "\n" << r.err;
    EXPECT_THAT(r.err, HasSubstr("expected 0 (in memory) or at least 4")) << bad;
  }
  EXPECT_TRUE(ListVolumes(server.address()).empty()) << "nothing uploaded";
  CliResult r = RunCli(server.address(), {"submit", volume_.string(), "--stream-slab-voxels", "4",
                                          "--min-psnr", "40"});
  EXPECT_NE(r.rc, 0) << r.err;
  EXPECT_THAT(r.err, HasSubstr("spec.stream_slab_voxels"));
  EXPECT_THAT(r.err, HasSubstr("no PSNR floor"));

  // The phantom's 7 cube layers in slabs of 4: two windows.
  const fs::path out = scratch_ / "streamed";
  r = RunCli(server.address(),
             {"submit", volume_.string(), "--stream-slab-voxels", "4", "--reduction", "0.3",
              "--image-size", "32", "--outputs", "vtu", "--watch", "--out", out.string()});
  ASSERT_EQ(r.rc, 0) << r.err;
  const std::string job = FirstLine(r.out);
  CliResult w = RunCli(server.address(), {"watch", job, "-o", "json"});
  EXPECT_EQ(w.rc, 0) << w.err;
  // Measuring passes over the slabs find the cost threshold, then the final pass makes the mesh
  // and the refit completes the stage. The job thins its progress events out (at most a few a
  // second), but keeps a stage's first and the one that completes it.
  std::vector<std::string> simplify;
  for (const auto& l : Lines(w.out)) {
    auto j = nlohmann::json::parse(l, nullptr, false);
    ASSERT_FALSE(j.is_discarded()) << l;
    if (j.value("/progress/stage"_json_pointer, std::string()) != "simplify") continue;
    const std::string message = j.value("/progress/message"_json_pointer, std::string());
    simplify.push_back(message.substr(0, message.find(" (")));
  }
  ASSERT_GE(simplify.size(), 2u) << w.out;
  EXPECT_EQ(simplify.front(), "slab 1 of 2, measuring pass 1") << w.out;
  EXPECT_THAT(simplify.back(), HasSubstr("values refit to")) << w.out;
  r = RunCli(server.address(), {"status", job});
  EXPECT_EQ(r.rc, 0) << r.err;
  EXPECT_THAT(r.out, HasSubstr("simplified in slabs of 4 voxel layers"));
  auto metrics = nlohmann::json::parse(ReadFile(out / "metrics.json"), nullptr, false);
  ASSERT_TRUE(metrics.is_object()) << ReadFile(out / "metrics.json");
  EXPECT_EQ(metrics["simplification"]["stream_slab_voxels"], 4);
  EXPECT_THAT(metrics["simplification"]["stop_message"].get<std::string>(),
              HasSubstr("in 2 windows of 4 voxel layers"));
  EXPECT_EQ(metrics["fidelity"]["label_mismatch"], 0.0);
  EXPECT_TRUE(fs::exists(out / "mesh.vtu"));
}

TEST_F(CliE2E, ListIsATableAndJsonLinesWithTheFlagBeforeOrAfterTheVerb) {
  ServerProcess server(scratch_ / "data");
  TwoSucceededJobs(server);
  CliResult r = RunCli(server.address(), {"list"});
  ASSERT_EQ(r.rc, 0) << r.err;
  std::vector<std::string> lines = Lines(r.out);
  ASSERT_EQ(lines.size(), 3u) << r.out;
  EXPECT_THAT(lines[0], ::testing::MatchesRegex(
                            "NAME +STATE +STAGE % +INPUT +K +REDUCTION +CREATED +DURATION"));
  EXPECT_THAT(lines[1], HasSubstr("SUCCEEDED"));
  EXPECT_THAT(lines[1], HasSubstr("phantom.nii"));
  EXPECT_THAT(lines[1], HasSubstr("30%"));
  // -o json / --json after the subcommand (as the README writes it), and the global one.
  for (auto args :
       {std::vector<std::string>{"list", "--json"}, std::vector<std::string>{"list", "-o", "JSON"},
        std::vector<std::string>{"--json", "list"}}) {
    r = RunCli(server.address(), args);
    ASSERT_EQ(r.rc, 0) << r.err;
    lines = Lines(r.out);
    ASSERT_EQ(lines.size(), 2u) << r.out;
    for (const auto& l : lines) {
      auto j = nlohmann::json::parse(l, nullptr, false);
      ASSERT_TRUE(j.is_object()) << l;
      EXPECT_EQ(j["state"], "SUCCEEDED");
    }
  }
}

TEST_F(CliE2E, ListWideShowsTheAchievedReductionAndStatesAreChecked) {
  ServerProcess server(scratch_ / "data");
  TwoSucceededJobs(server);
  CliResult r = RunCli(server.address(), {"list", "-o", "wide", "--state", "succeeded"});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_THAT(r.out, HasSubstr("ACHIEVED"));
  // REDUCTION (the target), CREATED, DURATION, then ACHIEVED: at least the target.
  const std::regex achieved_column(R"(  30%\s+[0-9-]+ [0-9:]+\s+[0-9:]+\s+3[0-9]\.[0-9]%\s)");
  EXPECT_TRUE(std::regex_search(r.out, achieved_column)) << r.out;
  EXPECT_EQ(RunCli(server.address(), {"list", "--state", "running"}).out, "");
  EXPECT_EQ(RunCli(server.address(), {"list", "--state", "done"}).rc, 2);
}

TEST_F(CliE2E, ListPagesSayHowToGoOnAndAllFollowsThem) {
  ServerProcess server(scratch_ / "data");
  TwoSucceededJobs(server);
  // One job per page says how to go on; the token gives the other; --all follows.
  CliResult r = RunCli(server.address(), {"list", "--page-size", "1"});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_EQ(Lines(r.out).size(), 2u) << r.out;
  const std::string more = "more: --page-token ";
  ASSERT_THAT(r.err, HasSubstr(more));
  std::string token = r.err.substr(r.err.find(more) + more.size());
  token = token.substr(0, token.find(' '));
  CliResult next = RunCli(server.address(), {"list", "--page-size", "1", "--page-token", token});
  ASSERT_EQ(next.rc, 0) << next.err;
  ASSERT_EQ(Lines(next.out).size(), 2u) << next.out;
  EXPECT_NE(Lines(next.out)[1], Lines(r.out)[1]);
  r = RunCli(server.address(), {"list", "--page-size", "1", "--all", "-o", "json"});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_EQ(Lines(r.out).size(), 2u) << r.out;
  EXPECT_THAT(r.out, ::testing::Not(HasSubstr("next_page_token")));
  r = RunCli(server.address(), {"list", "--page-size", "1", "-o", "json"});
  EXPECT_THAT(r.out, HasSubstr("{\"next_page_token\":"));
}

TEST_F(CliE2E, StatusDescribesAJobFoundByItsShortestUniquePrefix) {
  ServerProcess server(scratch_ / "data");
  const std::vector<std::string> jobs = TwoSucceededJobs(server);
  size_t n = 1;
  while (jobs[0].substr(0, n) == jobs[1].substr(0, n)) ++n;
  CliResult r = RunCli(server.address(), {"status", jobs[0].substr(0, n)});
  ASSERT_EQ(r.rc, 0) << r.err;
  for (const char* key :
       {"Name:", "State:", "Input:", "Spec:", "Times:", "Result:", "Artifacts:", "mesh.vtu"}) {
    EXPECT_THAT(r.out, HasSubstr(key));
  }
  ExpectReductionLine(r.out, 30.0);
  EXPECT_THAT(r.out, HasSubstr(jobs[0]));
  r = RunCli(server.address(), {"describe", jobs[1], "-o", "json"});
  ASSERT_EQ(r.rc, 0);
  EXPECT_TRUE(nlohmann::json::parse(r.out, nullptr, false).is_object()) << r.out;
  EXPECT_EQ(RunCli(server.address(), {"status", "zzzz"}).rc, 6);
}

TEST_F(CliE2E, VersionOfBothPrograms) {
  CliResult r = RunProgram({CliBinary().string(), "--version"});
  EXPECT_EQ(r.rc, 0);
  EXPECT_THAT(r.out, HasSubstr("decima "));
  CliResult sv = RunProgram({ServerBinary().string(), "--version"});
  EXPECT_EQ(sv.rc, 0) << sv.err;
  EXPECT_THAT(sv.out, HasSubstr("decima-server "));
}

TEST_F(CliE2E, DeleteRemovesAJobAndPruneIsADryRunUntilForced) {
  ServerProcess server(scratch_ / "data");
  const std::vector<std::string> jobs = TwoSucceededJobs(server);
  CliResult r = RunCli(server.address(), {"delete", jobs[0]});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_THAT(r.out, HasSubstr("deleted jobs/" + jobs[0]));
  EXPECT_EQ(RunCli(server.address(), {"status", jobs[0]}).rc, 6);
  EXPECT_FALSE(fs::exists(server.data_dir() / "jobs" / jobs[0]));
  r = RunCli(server.address(), {"prune"});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_THAT(r.out, HasSubstr("would delete jobs/" + jobs[1]));
  EXPECT_THAT(r.err, HasSubstr("--force"));
  EXPECT_EQ(RunCli(server.address(), {"status", jobs[1]}).rc, 0);  // still there
  EXPECT_FALSE(ListVolumes(server.address()).empty());
  r = RunCli(server.address(), {"prune", "--force"});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_THAT(r.out, HasSubstr("deleted jobs/" + jobs[1]));
  EXPECT_EQ(RunCli(server.address(), {"list", "--json"}).out, "");
  EXPECT_TRUE(ListVolumes(server.address()).empty());
}

TEST_F(CliE2E, WrongAddressFailsFastWithAHintAndAWatchThatLosesTheServerSaysSoOnce) {
  // Nothing listens on a port we just closed.
  const auto t0 = std::chrono::steady_clock::now();
  CliResult r = RunCli("127.0.0.1:1", {"list"});
  EXPECT_EQ(r.rc, 8);
  EXPECT_LT(std::chrono::steady_clock::now() - t0, 10s);
  EXPECT_THAT(r.err, HasSubstr("cannot reach decima-server at 127.0.0.1:1"));
  EXPECT_THAT(r.err, HasSubstr("--server"));
  EXPECT_THAT(r.err, HasSubstr("DECIMA_SERVER"));
  r = RunCli("127.0.0.1:1", {"watch", "0123456789abcdef"});
  EXPECT_EQ(r.rc, 8);
  EXPECT_LE(Lines(r.err).size(), 2u) << r.err;

  // --allow-faults: without it the sleep fault is ignored, the job really runs, and the number of
  // progress lines before the kill depends on the machine's speed.
  ServerProcess server(scratch_ / "data", {"--allow-faults"});
  CliResult s = RunCli(server.address(), {"submit", volume_.string(), "--fault", "sleep:30"});
  ASSERT_EQ(s.rc, 0) << s.err;
  CliProcess w = StartCli(server.address(), {"--reconnect", "2", "watch", FirstLine(s.out)});
  ASSERT_TRUE(WaitFor([&] { return ReadFile(w.err).find("watching") != std::string::npos; }, 20s));
  server.Kill(SIGKILL);
  r = WaitCli(w, 30s);
  EXPECT_EQ(r.rc, 8) << r.err;
  // One line for the lost server (not one per attempt), one for giving up, then the error.
  EXPECT_EQ(CountOf(r.err, "server unavailable"), 1) << r.err;
  EXPECT_EQ(CountOf(r.err, "gave up after"), 1) << r.err;
  EXPECT_LE(Lines(r.err).size(), 8u) << r.err;
}

TEST_F(CliE2E, PlainProgressLinesCleanStartAndCtrlCSaysHowToReattach) {
  // --allow-faults: the Ctrl-C part needs a job that is still running (a sleep fault).
  ServerProcess server(scratch_ / "data", {"--allow-faults"});
  CliResult r = RunCli(server.address(), {"submit", volume_.string(), "--watch", "--image-size",
                                          "32", "--reduction", "0.3"});
  ASSERT_EQ(r.rc, 0) << r.err;
  // Not a TTY: plain lines with the overall %, elapsed; no internal sequence numbers.
  EXPECT_THAT(r.err, HasSubstr("elapsed "));
  EXPECT_THAT(r.err, Not(HasSubstr(" #")));
  EXPECT_THAT(r.err, Not(HasSubstr("snapshot")));
  EXPECT_THAT(r.err, Not(HasSubstr("\r")));
  EXPECT_EQ(CountOf(r.err, "decima: watching jobs/"), 1) << r.err;
  std::regex overall(R"( (\d+)% (load|segment|tetra|simplify|write|render|diff) \d+%)");
  int last = -1, count = 0;
  for (const auto& l : Lines(r.err)) {
    std::smatch m;
    if (std::regex_search(l, m, overall)) {
      const int pct = std::stoi(m[1]);
      EXPECT_GE(pct, last) << l;  // the overall bar never goes back
      last = pct;
      ++count;
    }
  }
  EXPECT_GE(count, 3) << r.err;
  EXPECT_EQ(last, 100) << r.err;

  CliResult s = RunCli(server.address(), {"submit", volume_.string(), "--fault", "sleep:30"});
  ASSERT_EQ(s.rc, 0) << s.err;
  const std::string job = FirstLine(s.out);
  CliProcess w = StartCli(server.address(), {"watch", job});
  ASSERT_TRUE(WaitFor([&] { return ReadFile(w.err).find("watching") != std::string::npos; }, 20s));
  kill(w.pid, SIGINT);
  r = WaitCli(w, 10s);
  EXPECT_EQ(r.rc, 130);
  EXPECT_THAT(r.err, HasSubstr("the job goes on on the server"));
  EXPECT_THAT(r.err, HasSubstr("re-attach: decima --server " + server.address() + " watch " +
                               job.substr(5)));
  EXPECT_EQ(RunCli(server.address(), {"cancel", job}).rc, 0);
}

TEST_F(CliE2E, InputsAsTheyComeViewsAndReusedRequestIds) {
  ServerProcess server(scratch_ / "data");
  // MetaImage header + data file: both go up, the job runs.
  const fs::path mhd = scratch_ / "tiny.mhd";
  {
    std::ofstream(mhd) << "ObjectType = Image\nNDims = 3\nDimSize = 12 10 8\n"
                          "ElementSpacing = 2 2 2\nElementType = MET_SHORT\n"
                          "ElementDataFile = tiny.raw\n";
    std::ofstream raw(scratch_ / "tiny.raw", std::ios::binary);
    // A bright ball in a darker box, as WriteTinyNifti draws it.
    for (int z = 0; z < 8; ++z) {
      for (int y = 0; y < 10; ++y) {
        for (int x = 0; x < 12; ++x) {
          const double r2 = (x - 5.5) * (x - 5.5) + (y - 4.5) * (y - 4.5) + (z - 3.5) * (z - 3.5);
          const int16_t v = static_cast<int16_t>(r2 < 9 ? 1000 : 100 + (x * 7 + y * 3 + z) % 5);
          raw.write(reinterpret_cast<const char*>(&v), 2);
        }
      }
    }
  }
  CliResult r = RunCli(server.address(),
                       {"submit", mhd.string(), "--watch", "--image-size", "32", "--reduction",
                        "0.05", "--views", "anterior,30,20", "--view", "-45:10"});
  ASSERT_EQ(r.rc, 0) << r.err << server.Log();
  EXPECT_THAT(r.err, HasSubstr("METAIMAGE"));
  const std::string job = FirstLine(r.out);
  r = RunCli(server.address(), {"status", job, "-o", "json"});
  auto j = nlohmann::json::parse(r.out, nullptr, false);
  ASSERT_TRUE(j.is_object()) << r.out;
  EXPECT_EQ(j["spec"]["views"], nlohmann::json({"anterior", "30:20", "-45:10"}));
  // Every view's pictures, named by the view.
  const fs::path out = scratch_ / "views";
  ASSERT_EQ(RunCli(server.address(), {"fetch", job, "--out", out.string(), "--only", "images"}).rc,
            0);
  for (const char* f : {"original.png", "comparison-az30_el20.png", "diff-az-45_el10.png"}) {
    EXPECT_TRUE(fs::exists(out / f)) << f;
  }
  // The pictures carry their parameters as PNG text.
  auto text = ReadPngText(out / "comparison-az30_el20.png");
  ASSERT_TRUE(text.ok()) << text.status();
  std::map<std::string, std::string> kv(text->begin(), text->end());
  EXPECT_EQ(kv["decima:view"], "30:20");
  EXPECT_EQ(kv["decima:job"], job);
  EXPECT_EQ(kv["Source"], "tiny.mhd");
  EXPECT_EQ(kv["decima:policy"], "field");
  EXPECT_FALSE(kv["decima:heat_scale_max"].empty());

  // A reused request id: the same spec returns the same job, another spec is refused.
  r = RunCli(server.address(),
             {"submit", volume_.string(), "--request-id", "rid-7", "--image-size", "32"});
  ASSERT_EQ(r.rc, 0) << r.err;
  const std::string first = FirstLine(r.out);
  r = RunCli(server.address(),
             {"submit", volume_.string(), "--request-id", "rid-7", "--image-size", "32"});
  ASSERT_EQ(r.rc, 0) << r.err;
  EXPECT_EQ(FirstLine(r.out), first);
  r = RunCli(server.address(),
             {"submit", volume_.string(), "--request-id", "rid-7", "--image-size", "48"});
  EXPECT_EQ(r.rc, 1);
  EXPECT_THAT(r.err, HasSubstr("ALREADY_EXISTS"));
  EXPECT_THAT(r.err, HasSubstr(first));
}

TEST_F(CliE2E, DicomFolderWithStrayFilesSkipsThemWithAWarning) {
  DECIMA_REQUIRE_SHARED_DATA(dicom, "ct-head-256x256x113-dicom");
  ServerProcess server(scratch_ / "data");
  // Copies (never hard links: writing a stray file must not reach the shared folder), plus a
  // DICOMDIR and a note beside the images.
  const fs::path folder = scratch_ / "series";
  fs::create_directories(folder);
  int images = 0, others = 0;
  for (const auto& e : fs::directory_iterator(dicom)) {
    if (!e.is_regular_file()) continue;
    fs::copy_file(e.path(), folder / e.path().filename());
    const std::string head = ReadFile(e.path()).substr(0, 132);
    (head.size() == 132 && head.compare(128, 4, "DICM") == 0 ? images : others) += 1;
  }
  ASSERT_FALSE(fs::exists(folder / "DICOMDIR"));
  ASSERT_FALSE(fs::exists(folder / "notes.txt"));
  std::ofstream(folder / "notes.txt") << "scanned on the old CT\n";
  std::ofstream(folder / "DICOMDIR") << "a directory record, not an image";
  CliResult r = RunCli(server.address(), {"submit", folder.string()});
  ASSERT_EQ(r.rc, 0) << r.err << server.Log();
  EXPECT_THAT(r.err, HasSubstr("warning: skipping " + std::to_string(others + 2) + " file(s)"));
  EXPECT_THAT(r.err, HasSubstr("notes.txt"));
  EXPECT_THAT(r.err, HasSubstr("DICOMDIR"));
  EXPECT_THAT(r.err, HasSubstr("VOLUME_FORMAT_DICOM"));
  auto vols = ListVolumes(server.address());
  ASSERT_EQ(vols.size(), 1u);
  EXPECT_EQ(vols[0].files_size(), images);
  EXPECT_EQ(RunCli(server.address(), {"cancel", FirstLine(r.out)}).rc, 0);
}

// report.html opens in a real browser: headless Chromium renders it to a non-empty screenshot
// and reports no console error. A page with a deliberate console error proves the check bites.
TEST_F(CliE2E, ReportRendersInHeadlessChromiumWithoutConsoleErrors) {
  const char* chromium = "/usr/bin/chromium";
  if (!fs::exists(chromium)) GTEST_SKIP() << "chromium is not installed (apt-get install chromium)";
  ServerProcess server(scratch_ / "data");
  const fs::path out = scratch_ / "report";
  CliResult r =
      RunCli(server.address(), {"submit", volume_.string(), "--out", out.string(), "--image-size",
                                "64", "--reduction", "0.3", "--only", "report"});
  ASSERT_EQ(r.rc, 0) << r.err;
  ASSERT_EQ(FilesIn(out), (std::set<std::string>{"report.html"}));
  const std::string html = ReadFile(out / "report.html");
  EXPECT_THAT(html, HasSubstr("data:image/png;base64,"));
  EXPECT_THAT(html, Not(HasSubstr("src=\"http")));    // self-contained
  EXPECT_THAT(html, HasSubstr("Reduction reached"));  // figures in words
  EXPECT_THAT(html, HasSubstr("Time per stage"));

  auto shoot = [&](const fs::path& page, const fs::path& png) {
    // WebGL (the report's 3D view) on SwiftShader, as tests/core/pipeline/report_test.cc.
    return RunProgram({chromium, "--headless", "--no-sandbox", "--use-angle=swiftshader",
                       "--enable-unsafe-swiftshader", "--virtual-time-budget=8000",
                       "--user-data-dir=" + (scratch_ / "chromium-profile").string(),
                       "--screenshot=" + png.string(), "--window-size=1000,1400",
                       "--enable-logging=stderr", "--v=0", "file://" + page.string()},
                      120s);
  };
  const fs::path bad = scratch_ / "bad.html";
  std::ofstream(bad) << "<!DOCTYPE html><html><body>x<script>console.error('deliberate');"
                        "</script></body></html>";
  CliResult control = shoot(bad, scratch_ / "bad.png");
  ASSERT_THAT(control.err, HasSubstr("deliberate")) << "chromium does not log console errors";

  CliResult c = shoot(out / "report.html", scratch_ / "shot.png");
  ASSERT_EQ(c.rc, 0) << c.err;
  // The one console line a good page logs: the 3D view's first frame.
  EXPECT_THAT(c.err, HasSubstr("decima-3d: ready")) << c.err;
  std::string others;
  for (const absl::string_view line : absl::StrSplit(c.err, '\n')) {
    if (absl::StrContains(line, "CONSOLE") && !absl::StrContains(line, "decima-3d: ready")) {
      absl::StrAppend(&others, line, "\n");
    }
  }
  EXPECT_EQ(others, "") << c.err;
  EXPECT_THAT(c.err, Not(HasSubstr("Uncaught"))) << c.err;
  auto shot = ReadPng(scratch_ / "shot.png");
  ASSERT_TRUE(shot.ok()) << shot.status();
  EXPECT_EQ(shot->width, 1000);
  // Non-empty: the page drew text, tables and the pictures, not one flat colour.
  std::set<uint32_t> colours;
  for (size_t i = 0; i + 2 < shot->pixels.size(); i += shot->channels) {
    colours.insert(shot->pixels[i] << 16 | shot->pixels[i + 1] << 8 | shot->pixels[i + 2]);
  }
  EXPECT_GT(colours.size(), 50u);
}

}  // namespace
}  // namespace decima::e2e
