// Stage checkpoints: a job stopped right after a checkpoint resumes from it with outputs
// identical to an uninterrupted run; a checkpoint of another spec, a damaged one or a torn one
// is ignored; the payload parsers refuse every truncation. And the peak-memory keys of
// metrics.json.
#include "core/pipeline/checkpoint.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>

#include <algorithm>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>

#include "core/io/volume_io.h"
#include "core/pipeline/pipeline.h"
#include "core/volume/phantom.h"
#include "tests/testing/test_data.h"

namespace decima::pipeline {
namespace {

namespace fs = std::filesystem;
using ::testing::ElementsAre;
using ::testing::HasSubstr;
using Json = nlohmann::json;

fs::path PhantomFile(const fs::path& dir) {
  HeadPhantomOptions o;
  o.dims = {24, 24, 20};
  o.spacing = {2, 2, 2};
  o.noise_sigma = 20;
  auto p = MakeHeadPhantom(o);
  EXPECT_TRUE(p.ok()) << p.status();
  const fs::path path = dir / "phantom.nii.gz";
  EXPECT_TRUE(io::WriteNifti(p->image, path).ok());
  return path;
}

JobSpec SmallSpec(const fs::path& input) {
  JobSpec s;
  s.input = input;
  s.image_size = 48;
  s.outputs = {"vtu", "labels"};
  return s;
}

std::string ReadAll(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

// metrics.json without what differs between two runs of the same job by design: timings,
// memory and which stages were resumed.
Json Comparable(const std::string& metrics_json) {
  Json j = Json::parse(metrics_json);
  // What depends on the clock or the machine: times, the ETA's forecasts, memory.
  for (const char* k : {"seconds", "eta", "peak_rss_mb", "stage_peak_rss_mb",
                        "stage_peak_rss_per_stage", "resumed_stages", "resumed_simplify_windows"}) {
    j.erase(k);
  }
  return j;
}

struct Attempt {
  absl::StatusOr<JobResult> result;
  std::vector<std::string> messages;  // "stage: message" of every progress event
};

// Runs the job with checkpoints in `ckpt`; with `stop_after`, cancels right after that stage's
// checkpoint is saved (what a SIGTERM or SIGKILL at that boundary leaves behind).
Attempt RunWithCheckpoints(const JobSpec& spec, const fs::path& out, const fs::path& ckpt,
                           const std::string& stop_after = "") {
  CancelToken cancel;
  CheckpointOptions c;
  c.dir = ckpt;
  c.key = "volume-sha";
  c.on_saved = [&](const std::string& stage) {
    if (stage == stop_after) cancel.Cancel();
  };
  Attempt run;
  run.result = RunJob(
      spec, out,
      [&](const Progress& p) { run.messages.push_back(absl::StrCat(p.stage, ": ", p.message)); },
      &cancel, c);
  return run;
}

// One uninterrupted run shared by the resume tests (the job is deterministic), each of which
// then interrupts and resumes its own copy in its own folders.
class ResumeTest : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    shared_ = decima::testing::MakeScratchDir("checkpoint");
    spec_ = SmallSpec(PhantomFile(shared_));
    auto r = RunJob(spec_, shared_ / "reference", nullptr, nullptr);
    ASSERT_TRUE(r.ok()) << r.status();
    reference_ = *r;
  }
  void SetUp() override { dir_ = decima::testing::MakeScratchDir("checkpoint"); }
  // The resumed run's outputs are the uninterrupted run's, byte for byte.
  void ExpectSameOutputs(const JobResult& r, const fs::path& out) {
    EXPECT_EQ(ReadAll(out / "mesh.vtu"), ReadAll(shared_ / "reference" / "mesh.vtu"));
    EXPECT_EQ(ReadAll(out / "labels.nii.gz"), ReadAll(shared_ / "reference" / "labels.nii.gz"));
    EXPECT_EQ(Comparable(r.metrics_json), Comparable(reference_.metrics_json));
  }
  static inline fs::path shared_;
  static inline JobSpec spec_;
  static inline JobResult reference_;
  fs::path dir_;
};

TEST_F(ResumeTest, StoppedAfterSegmentResumesFromTheSegmentationWithIdenticalOutputs) {
  const Attempt first = RunWithCheckpoints(spec_, dir_ / "a1", dir_ / "ckpt", "segment");
  ASSERT_EQ(first.result.status().code(), absl::StatusCode::kCancelled) << first.result.status();
  ASSERT_TRUE(fs::exists(dir_ / "ckpt" / "segment.ckpt"));
  EXPECT_FALSE(fs::exists(dir_ / "ckpt" / "simplify.ckpt"));

  const Attempt second = RunWithCheckpoints(spec_, dir_ / "a2", dir_ / "ckpt");
  ASSERT_TRUE(second.result.ok()) << second.result.status();
  EXPECT_THAT(second.messages, ::testing::Contains("segment: resumed from checkpoint"));
  EXPECT_EQ(Json::parse(second.result->metrics_json)["resumed_stages"], Json({"segment"}));
  ExpectSameOutputs(*second.result, dir_ / "a2");
}

TEST_F(ResumeTest, StoppedAfterSimplifyResumesFromTheSimplifiedMeshWithIdenticalOutputs) {
  const Attempt first = RunWithCheckpoints(spec_, dir_ / "a1", dir_ / "ckpt", "simplify");
  ASSERT_EQ(first.result.status().code(), absl::StatusCode::kCancelled) << first.result.status();
  ASSERT_TRUE(fs::exists(dir_ / "ckpt" / "simplify.ckpt"));

  const Attempt second = RunWithCheckpoints(spec_, dir_ / "a2", dir_ / "ckpt");
  ASSERT_TRUE(second.result.ok()) << second.result.status();
  EXPECT_EQ(Json::parse(second.result->metrics_json)["resumed_stages"],
            Json({"segment", "simplify"}));
  ExpectSameOutputs(*second.result, dir_ / "a2");
}

TEST_F(ResumeTest, ACheckpointOfAnotherSpecIsNotResumed) {
  ASSERT_EQ(
      RunWithCheckpoints(spec_, dir_ / "a1", dir_ / "ckpt", "simplify").result.status().code(),
      absl::StatusCode::kCancelled);
  // Another reduction: the segmentation still applies, the simplified mesh does not.
  JobSpec other = spec_;
  other.target_reduction = 0.3;
  const Attempt run = RunWithCheckpoints(other, dir_ / "a2", dir_ / "ckpt");
  ASSERT_TRUE(run.result.ok()) << run.result.status();
  const Json m = Json::parse(run.result->metrics_json);
  EXPECT_EQ(m["resumed_stages"], Json({"segment"}));
  EXPECT_THAT(run.messages, ::testing::Contains(HasSubstr("simplify: checkpoint ignored")));
  EXPECT_NEAR(m["simplification"]["achieved_reduction"].get<double>(), 0.3, 0.01);
  // Another volume (key): nothing is resumed.
  CheckpointOptions c;
  c.dir = dir_ / "ckpt";
  c.key = "another-volume-sha";
  auto r = RunJob(spec_, dir_ / "a3", nullptr, nullptr, c);
  ASSERT_TRUE(r.ok()) << r.status();
  EXPECT_EQ(Json::parse(r->metrics_json)["resumed_stages"], Json::array());
}

TEST_F(ResumeTest, ADamagedCheckpointIsIgnoredAndTheStageRunsAgain) {
  ASSERT_EQ(
      RunWithCheckpoints(spec_, dir_ / "a1", dir_ / "ckpt", "simplify").result.status().code(),
      absl::StatusCode::kCancelled);
  // One flipped bit in the simplified mesh's payload.
  const fs::path f = dir_ / "ckpt" / "simplify.ckpt";
  std::string bytes = ReadAll(f);
  ASSERT_GT(bytes.size(), 1000u);
  bytes[bytes.size() / 2] ^= 1;
  std::ofstream(f, std::ios::binary | std::ios::trunc) << bytes;
  const Attempt run = RunWithCheckpoints(spec_, dir_ / "a2", dir_ / "ckpt");
  ASSERT_TRUE(run.result.ok()) << run.result.status();
  EXPECT_THAT(run.messages, ::testing::Contains(HasSubstr("checksum mismatch")));
  EXPECT_EQ(Json::parse(run.result->metrics_json)["resumed_stages"], Json({"segment"}));
  ExpectSameOutputs(*run.result, dir_ / "a2");
}

// The window records of a streamed simplify stage (StreamJournal in checkpoint files).
std::vector<std::string> WindowRecords(const fs::path& ckpt) {
  std::vector<std::string> names;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(ckpt, ec)) {
    const std::string name = e.path().filename().string();
    if (name.rfind(kSimplifyWindowRecordPrefix, 0) == 0) names.push_back(name);
  }
  std::sort(names.begin(), names.end());
  return names;
}

// A job stopped inside a streamed simplify stage (right after its third window's record) resumes
// after that window, not from the stage's start, with the outputs of a run in one go; a damaged
// record is simplified again from there; the stage's own checkpoint replaces the records.
TEST_F(ResumeTest, AStreamedSimplifyStageStoppedMidwayResumesAfterItsLastSavedWindow) {
  JobSpec spec = spec_;
  spec.stream_slab_voxels = 4;  // 19 cube layers: 5 windows a pass
  spec.target_reduction = 0.8;
  auto plain = RunJob(spec, dir_ / "plain", nullptr, nullptr);
  ASSERT_TRUE(plain.ok()) << plain.status();
  const Json plain_metrics = Json::parse(plain->metrics_json);
  ASSERT_EQ(plain_metrics["simplification"]["stream_slab_voxels"], 4);
  EXPECT_FALSE(plain_metrics.contains("resumed_simplify_windows"));

  // The disk the stage's checkpoints take at most, against the estimate the server admits.
  {
    const fs::path ckpt = dir_ / "ckpt-size";
    CheckpointOptions c;
    c.dir = ckpt;
    c.key = "volume-sha";
    int64_t peak = 0;
    c.on_saved = [&](const std::string&) {
      int64_t bytes = 0;
      for (const auto& e : fs::directory_iterator(ckpt)) {
        const std::string name = e.path().filename().string();
        if (name.rfind("simplify", 0) == 0) bytes += int64_t(fs::file_size(e.path()));
      }
      peak = std::max(peak, bytes);
    };
    auto sized = RunJob(spec, dir_ / "sized", nullptr, nullptr, c);
    ASSERT_TRUE(sized.ok()) << sized.status();
    const int64_t estimate = StreamRecordBytes(24 * 24 * 20, 0.8);
    EXPECT_GT(peak, 0);
    EXPECT_LE(peak, estimate);
    EXPECT_GE(peak, estimate / 3) << "an estimate this far above is no use for admission";
  }

  for (const bool damage : {false, true}) {
    const fs::path ckpt = dir_ / (damage ? "ckpt-damaged" : "ckpt");
    const Attempt first = RunWithCheckpoints(spec, dir_ / "a1", ckpt, "simplify-window-3");
    ASSERT_EQ(first.result.status().code(), absl::StatusCode::kCancelled) << first.result.status();
    EXPECT_THAT(WindowRecords(ckpt),
                ElementsAre("simplify.pass-0.window-0.ckpt", "simplify.pass-0.window-1.ckpt",
                            "simplify.pass-0.window-2.ckpt"));
    EXPECT_FALSE(fs::exists(ckpt / "simplify.ckpt"));
    if (damage) {
      // One flipped bit in window 1's record: window 0 is read back, the rest simplified again.
      const fs::path f = ckpt / "simplify.pass-0.window-1.ckpt";
      std::string bytes = ReadAll(f);
      bytes[bytes.size() / 2] ^= 1;
      std::ofstream(f, std::ios::binary | std::ios::trunc) << bytes;
    }
    const Attempt second = RunWithCheckpoints(spec, dir_ / "a2", ckpt);
    ASSERT_TRUE(second.result.ok()) << second.result.status();
    const Json metrics = Json::parse(second.result->metrics_json);
    EXPECT_EQ(metrics["resumed_stages"], Json({"segment", "simplify"}));
    EXPECT_EQ(metrics["resumed_simplify_windows"], damage ? 1 : 3);
    EXPECT_THAT(second.messages,
                ::testing::Contains(
                    HasSubstr(damage ? "resumed after slab 1 of 5" : "resumed after slab 3 of 5")));
    EXPECT_EQ(ReadAll(dir_ / "a2" / "mesh.vtu"), ReadAll(dir_ / "plain" / "mesh.vtu"));
    EXPECT_EQ(Comparable(second.result->metrics_json), Comparable(plain->metrics_json));
    EXPECT_TRUE(fs::exists(ckpt / "simplify.ckpt"));
    EXPECT_THAT(WindowRecords(ckpt), ::testing::IsEmpty()) << "replaced by simplify.ckpt";
  }
}

// A checkpoint holds the simplified mesh, not its collapse record: a levels job resumed after
// simplify runs the simplification again for the record, which is the uninterrupted run's.
TEST_F(ResumeTest, ALevelsJobResumedAfterSimplifyWritesTheSameRecord) {
  JobSpec spec = spec_;
  spec.outputs = {"vtu", "levels"};
  spec.record_levels_to = 0.7;
  auto plain = RunJob(spec, dir_ / "plain", nullptr, nullptr);
  ASSERT_TRUE(plain.ok()) << plain.status();
  const Attempt first = RunWithCheckpoints(spec, dir_ / "a1", dir_ / "ckpt", "simplify");
  ASSERT_EQ(first.result.status().code(), absl::StatusCode::kCancelled) << first.result.status();
  const Attempt second = RunWithCheckpoints(spec, dir_ / "a2", dir_ / "ckpt");
  ASSERT_TRUE(second.result.ok()) << second.result.status();
  EXPECT_EQ(Json::parse(second.result->metrics_json)["resumed_stages"],
            Json({"segment", "simplify"}));
  const std::string record = ReadAll(dir_ / "plain" / "mesh.levels");
  EXPECT_GT(record.size(), 72u);
  EXPECT_EQ(ReadAll(dir_ / "a2" / "mesh.levels"), record);
  EXPECT_EQ(ReadAll(dir_ / "a2" / "mesh.vtu"), ReadAll(dir_ / "plain" / "mesh.vtu"));
  // The floor is part of the checkpoint's key: a job without levels does not resume it.
  const Attempt without = RunWithCheckpoints(spec_, dir_ / "a3", dir_ / "ckpt");
  ASSERT_TRUE(without.result.ok()) << without.result.status();
  EXPECT_EQ(Json::parse(without.result->metrics_json)["resumed_stages"], Json({"segment"}));
  ExpectSameOutputs(*without.result, dir_ / "a3");
}

TEST(Checkpoint, ATornOrForeignFileIsRefusedAndAMissingOneIsNotFound) {
  const fs::path dir = decima::testing::MakeScratchDir("checkpoint");
  const fs::path f = dir / "x.ckpt";
  EXPECT_EQ(ReadCheckpoint(f, "k").status().code(), absl::StatusCode::kNotFound);
  ASSERT_TRUE(WriteCheckpoint(f, "k", std::string(100, 'p')).ok());
  auto ok = ReadCheckpoint(f, "k");
  ASSERT_TRUE(ok.ok()) << ok.status();
  EXPECT_EQ(*ok, std::string(100, 'p'));
  EXPECT_FALSE(fs::exists(dir / "x.ckpt.tmp")) << "the temporary file was renamed";
  EXPECT_THAT(ReadCheckpoint(f, "other").status().message(), HasSubstr("key differs"));
  const std::string whole = ReadAll(f);
  std::ofstream(f, std::ios::binary | std::ios::trunc) << whole.substr(0, whole.size() - 1);
  EXPECT_EQ(ReadCheckpoint(f, "k").status().code(), absl::StatusCode::kFailedPrecondition);
  std::ofstream(f, std::ios::binary | std::ios::trunc) << "not a checkpoint";
  EXPECT_THAT(ReadCheckpoint(f, "k").status().message(), HasSubstr("bad magic"));
}

// The simplify stage writes its checkpoint as it serializes it (no copy of a clinical scan's
// mesh in memory): the file must be the string version's byte for byte, with arrays larger than
// the writer's block (handed to the file from the array) between small values (gathered).
TEST(Checkpoint, AStreamedPayloadWritesTheSameFileAsItsString) {
  const fs::path dir = decima::testing::MakeScratchDir("checkpoint-streamed");
  SimplifyResult s;
  const int32_t n = 300000;  // positions alone are 3.6 MB, over ByteWriter::kSinkBlock
  for (int32_t v = 0; v < n; ++v) {
    for (int k = 0; k < 3; ++k) s.mesh.positions.push_back(float(v % 97) + 0.25f * float(k));
    s.mesh.scalars.push_back(float(v) * 0.5f);
    s.mesh.labels.push_back(uint8_t(v % 3));
    s.mesh.interface_distance.push_back(float(v % 11));
    s.mesh.vertex_flags.push_back(uint8_t(v % 5));
    s.vertex_map.push_back(v / 2);
  }
  for (int32_t c = 0; c + 3 < n; c += 3) {
    for (int k = 0; k < 4; ++k) s.mesh.tets.push_back(c + k);
    s.mesh.cell_regions.push_back(uint8_t(c % 3));
  }
  s.input_cells = 5 * int64_t(n);
  s.output_cells = s.mesh.tet_count();
  s.stop_message = "target reached";
  s.pass_stats.resize(3);
  const std::string payload = SerializeSimplifyResult(s);
  ASSERT_GT(payload.size(), 3 * ByteWriter::kSinkBlock);
  ASSERT_TRUE(WriteCheckpoint(dir / "string.ckpt", "key", payload).ok());
  absl::Status st = WriteCheckpoint(dir / "streamed.ckpt", "key",
                                    [&](ByteWriter& w) { PutSimplifyResult(w, s); });
  ASSERT_TRUE(st.ok()) << st;
  EXPECT_EQ(ReadAll(dir / "streamed.ckpt"), ReadAll(dir / "string.ckpt"));
  auto back = ReadCheckpoint(dir / "streamed.ckpt", "key");
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(*back, payload);
  EXPECT_FALSE(fs::exists(dir / "streamed.ckpt.tmp"));
  // A folder that cannot be made is named, and no file is left.
  std::ofstream(dir / "a-file") << "x";
  st = WriteCheckpoint(dir / "a-file" / "x.ckpt", "key",
                       [&](ByteWriter& w) { PutSimplifyResult(w, s); });
  EXPECT_EQ(st.code(), absl::StatusCode::kInternal);
  EXPECT_THAT(st.message(), HasSubstr("a-file"));
}

TEST(Checkpoint, PayloadsRoundTripAndEveryTruncationIsRefused) {
  SegmentResult seg;
  seg.labels.dims = {2, 2, 1};
  seg.labels.type = VoxelType::kUInt8;
  seg.labels.bytes = {0, 1, 1, 2};
  seg.labels.spacing = {0.5, 0.7, 1.1};
  seg.interface_distance_voxels = {0.5f, 0.5f, 1.5f, 0.5f};
  seg.interface_distance_mm = {0.25f, 0.25f, 0.75f, 0.25f};
  seg.class_means = {1.5, 2.25, 7};
  seg.region_voxels = {1, 2, 1};
  seg.iterations = 17;
  seg.converged = true;
  seg.energy = 0.1 + 0.2;  // not exactly representable: the bits must survive
  const std::string s = SerializeSegmentResult(seg);
  auto back = ParseSegmentResult(s);
  ASSERT_TRUE(back.ok()) << back.status();
  EXPECT_EQ(back->labels.bytes, seg.labels.bytes);
  EXPECT_EQ(back->labels.spacing, seg.labels.spacing);
  EXPECT_EQ(back->interface_distance_mm, seg.interface_distance_mm);
  EXPECT_EQ(back->class_means, seg.class_means);
  EXPECT_EQ(back->iterations, 17);
  EXPECT_TRUE(back->converged);
  EXPECT_EQ(back->energy, seg.energy);
  EXPECT_EQ(SerializeSegmentResult(*back), s);
  for (size_t n = 0; n < s.size(); ++n) {
    EXPECT_FALSE(ParseSegmentResult(s.substr(0, n)).ok()) << n << " of " << s.size() << " bytes";
  }

  SimplifyResult simp;
  simp.mesh.positions = {0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1};
  simp.mesh.scalars = {1, 2, 3, 4};
  simp.mesh.labels = {0, 0, 1, 1};
  simp.mesh.interface_distance = {0.5f, 0.5f, 0.5f, 0.5f};
  simp.mesh.vertex_flags = {1, 0, 0, 2};
  simp.mesh.tets = {0, 1, 2, 3};
  simp.mesh.cell_regions = {3};
  simp.vertex_map = {0, 1, -1, 2, 3};
  simp.stop_reason = StopReason::kStalled;
  simp.stop_message = "stalled";
  simp.pass_stats.resize(2);
  simp.pass_stats[1].last_error = 0.3;
  const std::string m = SerializeSimplifyResult(simp);
  auto mback = ParseSimplifyResult(m);
  ASSERT_TRUE(mback.ok()) << mback.status();
  EXPECT_EQ(mback->mesh.tets, simp.mesh.tets);
  EXPECT_EQ(mback->vertex_map, simp.vertex_map);
  EXPECT_EQ(mback->stop_reason, StopReason::kStalled);
  EXPECT_EQ(mback->pass_stats[1].last_error, 0.3);
  EXPECT_EQ(SerializeSimplifyResult(*mback), m);
  for (size_t n = 0; n < m.size(); ++n) {
    EXPECT_FALSE(ParseSimplifyResult(m.substr(0, n)).ok()) << n << " of " << m.size() << " bytes";
  }
  // A cell naming a vertex that does not exist is refused, not trusted.
  simp.mesh.tets[3] = 9;
  EXPECT_THAT(ParseSimplifyResult(SerializeSimplifyResult(simp)).status().message(),
              HasSubstr("mesh.tets"));
}

TEST(RunJobMetrics, ReportsThePeakResidentMemoryOverallAndPerStage) {
  const fs::path dir = decima::testing::MakeScratchDir("checkpoint");
  JobSpec spec = SmallSpec(PhantomFile(dir));
  auto r = RunJob(spec, dir / "out", nullptr, nullptr);
  ASSERT_TRUE(r.ok()) << r.status();
  const Json m = Json::parse(r->metrics_json);
  ASSERT_TRUE(m.contains("peak_rss_mb"));
  const double peak = m["peak_rss_mb"].get<double>();
  // Segmentation works on a float32 copy of the voxels: the peak holds at least that.
  const double voxel_mb = m["input"]["voxels"].get<double>() * 4 / (1 << 20);
  EXPECT_GT(peak, voxel_mb);
  EXPECT_LT(peak, 64 * 1024) << "a 24x24x20 job does not use 64 GiB";
  const Json& stages = m["stage_peak_rss_mb"];
  for (const char* s : {"load", "segment", "tetra", "simplify", "write", "render", "diff"}) {
    ASSERT_TRUE(stages.contains(s)) << s << " in " << stages.dump();
    EXPECT_GT(stages[s].get<double>(), 0) << s;
    EXPECT_LE(stages[s].get<double>(), peak + 1e-9) << s << ": no stage above the process peak";
  }
  EXPECT_TRUE(m["stage_peak_rss_per_stage"].get<bool>()) << "clear_refs resets VmHWM on Linux";
}

}  // namespace
}  // namespace decima::pipeline
